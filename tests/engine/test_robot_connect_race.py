"""Robot creation is serialised (issue 15): the browser's Calibrate step (``connect_robot``) and
another client's command may reach an unconnected session at the same time; they must share one
robot (one arm connection), never build two."""

import threading
import time

from monotracker.engine import Session, SessionConfig

from .doubles import FollowerRobotRig


def test_concurrent_connects_create_one_robot(tmp_path):
    made = []

    def slow_factory(cfg, session):
        made.append(threading.get_ident())
        time.sleep(0.3)  # a real arm connection (or control process start) takes a while
        return FollowerRobotRig()

    s = Session(SessionConfig(home=tmp_path / "home", clock="sim"), robot_factory=slow_factory)
    try:
        results = []
        go = threading.Barrier(4)

        def connect():
            go.wait()
            results.append(s.connect_robot())

        threads = [threading.Thread(target=connect) for _ in range(4)]
        for t in threads:
            t.start()
        for t in threads:
            t.join(timeout=60)
        assert len(results) == 4 and all(r.ok for r in results), [r.message for r in results]
        assert len(made) == 1
        rob = s._loop.robot.rig
        assert isinstance(rob, FollowerRobotRig) and s.connect_robot().ok and s._loop.robot.rig is rob
    finally:
        s.shutdown()
