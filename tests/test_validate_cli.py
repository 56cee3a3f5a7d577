"""``mocap validate`` through the CLI entry point."""

from __future__ import annotations

import session_builders as sb

from mocap.cli import main


def test_validate_good_session(tmp_path, capsys):
    spec = sb.session_2d("mixed")
    spec.manifest["operator"] = "kim"
    root = spec.write(tmp_path / "session")
    assert main(["validate", str(root)]) == 0
    out, err = capsys.readouterr()
    assert err == ""
    assert "tiny-2d" in out
    assert "fps       100" in out
    assert "2D blob detections" in out
    assert "cam1       1280 x 1024 px   focal 1200 px" in out
    assert "cam2       1280 x 1024 px   focal none" in out
    # response: one take, 5 frames, 30 blobs, 3 command rows
    assert any(line.split() == ["response", "1", "5", "30", "3"] for line in out.splitlines())
    assert "upper eyelid lowering  (feedback)" in out
    assert "unknown key 'operator'" in out
    assert "ok: the session meets the input contract" in out


def test_validate_3d_session(tmp_path, capsys):
    root = sb.session_3d("csv").write(tmp_path / "session")
    assert main(["validate", str(root)]) == 0
    out, _ = capsys.readouterr()
    assert "labeled 3D markers" in out
    # rest: one take, 5 frames, 15 samples of which 13 seen, no commands
    assert any(line.split() == ["rest", "1", "5", "15", "13", "0"] for line in out.splitlines())


def test_validate_bad_take_row(tmp_path, capsys):
    spec = sb.session_2d("csv")
    spec.table("smile_A").loc[5, "camera"] = "cam9"
    root = spec.write(tmp_path / "session")
    assert main(["validate", str(root)]) == 1
    out, err = capsys.readouterr()
    assert out == ""
    assert err.startswith("error: takes/smile_A.csv line 7: camera 'cam9' is not in the manifest")


def test_validate_bad_manifest(tmp_path, capsys):
    spec = sb.session_2d("csv")
    del spec.manifest["schema"]
    root = spec.write(tmp_path / "session")
    assert main(["validate", str(root)]) == 1
    _, err = capsys.readouterr()
    assert err.strip() == "error: session.toml: missing key 'schema' (expected \"mocap-session/1\")"
