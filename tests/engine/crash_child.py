"""Child process for the kill -9 test: runs the headless twin in HOME, tracking for a long time;
prints one line ``TRACKING <plan json>`` once tracking has started, then keeps tracking until
killed. Usage: python crash_child.py HOME"""

import json
import pathlib
import sys

from monotracker.demo.run import DemoOptions, run_demo


def main() -> None:
    home = pathlib.Path(sys.argv[1])
    def on_tracking(session):
        print("TRACKING " + json.dumps(session.plan_copy().to_dict()), flush=True)

    run_demo(DemoOptions(seconds=600.0, trajectory="breathing", home=home), on_tracking=on_tracking)


if __name__ == "__main__":
    main()
