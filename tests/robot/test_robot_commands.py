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


def test_robot_check_only_reads_and_never_takes_control(monkeypatch, capsys):
    """robot-check must not open an RTDE *control* interface: creating one uploads ur_rtde's
    control script, which stops whatever program the robot is running."""
    import numpy as np

    from fake_rtde import FakeUR
    from monotracker.robot import kinematics as kin
    from monotracker.robot import ur_rtde_arm

    ur = FakeUR(kin.Q_READY)
    opened = []

    def control(host, freq):
        opened.append(host)
        return ur.control(host, freq)

    monkeypatch.setattr(ur_rtde_arm, "_default_control", control)
    monkeypatch.setattr(ur_rtde_arm, "_default_receive", ur.receive)
    assert main(["robot-check", "10.0.0.2"]) == 0
    assert opened == []
    out = capsys.readouterr().out
    assert np.array2string(np.degrees(kin.Q_READY), precision=2)[:20] in out
    assert ("disconnect",) in ur.calls


def test_robot_check_without_robot_is_one_line(monkeypatch, capsys):
    from fake_rtde import FakeUR
    from monotracker.robot import kinematics as kin
    from monotracker.robot import ur_rtde_arm

    ur = FakeUR(kin.Q_READY, answer=False)
    monkeypatch.setattr(ur_rtde_arm, "_default_control", ur.control)
    monkeypatch.setattr(ur_rtde_arm, "_default_receive", ur.receive)
    assert main(["robot-check", "10.0.0.2"]) != 0
    err = capsys.readouterr().err.strip()
    assert err.startswith("error:") and "\n" not in err
