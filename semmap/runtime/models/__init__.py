"""The models a run needs and how they are had: the detector's weights (fetched and converted to ONNX without
torch, quantised), which configuration real time takes on this machine (measured), and ORB-SLAM3's vocabulary."""
