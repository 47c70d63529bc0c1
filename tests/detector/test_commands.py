"""`semmap models fetch` and `semmap detect` as registered by semmap.cli.models."""

from __future__ import annotations

import argparse
import json
import re

import pytest

from semmap.cli.models import register

from .tiny_yolo import tiny_checkpoint

LINE = re.compile(r"^(?P<cls>[a-z][a-z ]*) (?P<score>\d\.\d{3}) ([\d.]+) ([\d.]+) ([\d.]+) ([\d.]+)$")


def _run(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="semmap")
    register(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(argv)
    return args.func(args)


def test_parsing():
    parser = argparse.ArgumentParser(prog="semmap")
    register(parser.add_subparsers(dest="command", required=True))
    a = parser.parse_args(["detect", "a.jpg", "b.png", "--json", "--conf", "0.5", "--classes", "cup, chair"])
    assert a.images == ["a.jpg", "b.png"] and a.json and a.conf == 0.5 and a.classes == {"cup", "chair"}
    assert callable(a.func)
    f = parser.parse_args(["models", "fetch", "--dir", "/tmp/x", "--force"])
    assert str(f.dir) == "/tmp/x" and f.force and callable(f.func)
    with pytest.raises(SystemExit):
        parser.parse_args(["models"])


def test_detect_without_model_exits_2_with_hint(monkeypatch, tmp_path, capsys):
    monkeypatch.setenv("SEMMAP_MODEL_DIR", str(tmp_path))
    assert _run(["detect", "x.jpg"]) == 2
    assert "semmap models fetch" in capsys.readouterr().err


def test_fetch_bad_source_exits_1(tmp_path, capsys):
    pt = tmp_path / "yolov5s.pt"
    pt.write_bytes(tiny_checkpoint())
    assert _run(["models", "fetch", "--dir", str(tmp_path / "m"), "--source", str(pt)]) == 1
    assert "sha256 mismatch" in capsys.readouterr().err


@pytest.mark.needs_model
@pytest.mark.needs_data
def test_detect_text_output_and_unreadable_image(model_path, kitchen_dir, tmp_path, capsys):
    frame = kitchen_dir / "frame-000750.color.jpg"
    junk = tmp_path / "junk.jpg"
    junk.write_text("not an image")
    rc = _run(["detect", "--model", str(model_path), str(junk), str(frame), str(tmp_path / "missing.png")])
    out, err = capsys.readouterr()
    assert rc == 1
    assert "junk.jpg: not a decodable image" in err and "missing.png" in err
    lines = out.splitlines()
    assert lines[0] == str(frame)
    parsed = [LINE.match(line) for line in lines[1:]]
    assert parsed and all(parsed)
    assert {"cup", "chair"} <= {m["cls"] for m in parsed}


@pytest.mark.needs_model
@pytest.mark.needs_data
def test_detect_json(model_path, kitchen_dir, capsys):
    frame = kitchen_dir / "frame-000000.color.jpg"
    assert _run(["detect", "--json", "--classes", "cup", "--model", str(model_path), str(frame)]) == 0
    doc = json.loads(capsys.readouterr().out)
    (img,) = doc["images"]
    assert img["image"] == str(frame) and (img["width"], img["height"]) == (640, 480)
    assert img["detections"] and {d["class_name"] for d in img["detections"]} == {"cup"}
    assert len(img["detections"][0]["box"]) == 4
