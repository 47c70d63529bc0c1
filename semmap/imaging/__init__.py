"""Image codecs, the one layer between core and datasets: OpenCV lives here (and above), never in core.

`semmap.imaging.opencv` is the codec frames use by default (`semmap.core.messages.image_codec`).
"""
