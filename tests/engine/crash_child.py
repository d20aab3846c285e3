"""Child process for the kill -9 test: runs the headless twin in HOME, tracking for a long time;
prints one line ``TRACKING <plan json>`` once tracking has started, then keeps tracking until
killed. Usage: python crash_child.py HOME [--robot-double]"""

import json
import pathlib
import sys

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))  # tests/ for the doubles

from monotracker.engine.demo import DemoOptions, run_demo  # noqa: E402


def main() -> None:
    home = pathlib.Path(sys.argv[1])
    robot_factory = None
    if "--robot-double" in sys.argv:
        from engine.doubles import FollowerRobotRig

        robot_factory = lambda *a: FollowerRobotRig()  # noqa: E731

    def on_tracking(session):
        print("TRACKING " + json.dumps(session.plan_copy().to_dict()), flush=True)

    run_demo(DemoOptions(seconds=600.0, trajectory="breathing", home=home), robot_factory=robot_factory,
             on_tracking=on_tracking)


if __name__ == "__main__":
    main()
