import json
import subprocess
import sys

import pytest

from cylsfm import __version__
from cylsfm.cli import main


def test_version_and_help(capsys):
    with pytest.raises(SystemExit) as info:
        main(["--version"])
    assert info.value.code == 0
    assert __version__ in capsys.readouterr().out
    assert main([]) == 0
    assert "camera" in capsys.readouterr().out


def test_console_script_runs():
    out = subprocess.run(
        [sys.executable, "-m", "cylsfm.cli", "--help"], capture_output=True, text=True, check=True
    )
    assert "demo" in out.stdout


def test_camera_new_and_show(tmp_path, capsys):
    path = tmp_path / "camera.json"
    assert main(["camera", "new", str(path), "--width", "512", "--height", "128"]) == 0
    data = json.loads(path.read_text())
    assert data["model"] == "cylindrical" and data["width"] == 512 and data["cx"] == 256
    assert main(["camera", "show", str(path)]) == 0
    assert "wraps" in capsys.readouterr().out


def test_bad_camera_file_is_one_clear_line(tmp_path, capsys):
    bad = tmp_path / "camera.json"
    bad.write_text('{"model": "cylindrical", "width": 512}')
    assert main(["camera", "show", str(bad)]) == 2
    err = capsys.readouterr().err
    assert str(bad) in err and "missing key" in err and "Traceback" not in err
