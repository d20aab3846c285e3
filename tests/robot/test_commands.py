import json

from monotracker.cli import main


def test_calibrate_handeye_simulated(tmp_path, capsys):
    out = tmp_path / "he.json"
    assert main(["calibrate-handeye", "--simulate", "--n", "8", "--out", str(out)]) == 0
    assert json.loads(out.read_text())["n_poses"] == 8
    assert "error vs simulated truth" in capsys.readouterr().out


def test_calibrate_handeye_bad_file_is_one_line(tmp_path, capsys):
    p = tmp_path / "p.json"
    p.write_text("[]")
    assert main(["calibrate-handeye", "--poses", str(p)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error:") and "\n" not in err
