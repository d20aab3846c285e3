"""Hysteresis on freshness: the tracking state changes when the pose stream changes, not with
every late frame, and what the snapshot says agrees with what the arm does.

The camera doubles here deliver the true pose with a transport delay chosen per frame, the way a
loaded machine delays a pipeline (the simulated clock makes it deterministic)."""

import threading
import time

import pytest

from monotracker.engine import Session, SessionConfig
from monotracker.engine.rigs.base import PoseSample

from .conftest import plan_sample
from .doubles import FollowerRobotRig, TruthCameraRig

LIMIT = 0.15  # SessionConfig.max_pose_age_s


class DelayedCameraRig(TruthCameraRig):
    """Frames reach the estimator ``delay(t)`` seconds after capture (t: session clock)."""

    def __init__(self, delay, clock):
        super().__init__("still", noise_mm=0.05)
        self._delay, self._clock = delay, clock

    @property
    def transport_delay_s(self):
        return self._delay(self._clock())


@pytest.fixture
def make_sim(tmp_path):
    """Sessions each in their own folder (so two runs in one test do not share a plan or log)."""
    made = []

    def make(**kw):
        factories = {k: kw.pop(k) for k in ("camera_factory", "robot_factory") if k in kw}
        s = Session(SessionConfig(home=tmp_path / f"home{len(made)}", **kw), **factories)
        made.append(s)
        return s

    yield make
    for s in made:
        s.shutdown()


def _run(make_sim, delay, seconds, **cfg):
    """Track for ``seconds`` with the given delay schedule; returns (session, per-tick records)."""
    rob = FollowerRobotRig()
    steady_first = lambda t: delay(t) if t >= 1.0 else 0.04  # start on a steady stream
    s = make_sim(clock="sim", camera_factory=lambda *a: DelayedCameraRig(steady_first, a[4].clock),
                     robot_factory=lambda *a: rob, **cfg)
    plan_sample(s)
    assert s.start_camera().ok
    s.advance(0.5)
    assert s.arm("1234").ok and s.start_tracking().ok
    ticks = []

    loop = s._loop  # the hold state machine's own state, beside what the snapshot says

    def hook(t):
        snap_pose = s.snapshot().pose
        last = loop.last_trusted
        fresh = last is not None and t - last.t_capture <= LIMIT
        ticks.append((t, rob.state, rob.valid, rob.stamp, snap_pose, loop.holding_code, fresh))

    s.add_tick_listener(hook)
    s.advance(seconds)
    return s, ticks


def _transitions(ticks):
    states = [tk[1] for tk in ticks]
    return sum(1 for a, b in zip(states, states[1:]) if a != b)


def _hiccups(period):
    """30 fps pipeline, 40 ms delay, but one frame every ``period`` s takes 220 ms."""
    return lambda t: 0.22 if (t % period) < 1 / 30 else 0.04


def test_arm_never_follows_a_pose_older_than_the_limit(make_sim):
    for dwell in (0.0, 0.3):
        s, ticks = _run(make_sim, _hiccups(0.45), 8.0, resume_dwell_s=dwell)
        following = [tk for tk in ticks if tk[1] == "tracking"]
        assert following, "never tracked"
        assert all(t - stamp <= LIMIT + 1e-9 for t, _, _, stamp, *_ in following)


def test_a_flaky_stream_holds_once_instead_of_flapping(make_sim):
    """Hiccups every 0.45 s: without hysteresis the state flips at every hiccup; with it the arm
    holds through the flaky period and the operator sees one episode, not dozens."""
    _, base = _run(make_sim, _hiccups(0.45), 10.0, resume_dwell_s=0.0)
    s, hyst = _run(make_sim, _hiccups(0.45), 10.0)
    n_base, n_hyst = _transitions(base), _transitions(hyst)
    assert n_base >= 30  # ~2 per hiccup
    assert n_hyst <= 6, n_hyst
    rows = [e.code for e in s.audit_entries()]
    assert rows.count("pose_stale") <= 2 and rows.count("resumed") <= 2


def test_steady_stream_after_a_single_hiccup_resumes_after_the_dwell(make_sim):
    delay = lambda t: 0.3 if 2.0 <= t < 2.04 else 0.04  # one 300 ms hiccup at 2 s
    s, ticks = _run(make_sim, delay, 4.0)
    holding = [tk[0] for tk in ticks if tk[1] == "holding"]
    assert holding, "the hiccup must hold the arm"
    start, end = min(holding), max(holding)
    assert 2.0 + LIMIT - 0.05 <= start <= 2.0 + 0.3 + 0.05  # when the freshest pose got too old
    assert 0.3 <= end - start <= 0.3 + 0.35 + 0.1  # the stale gap, then the 0.3 s dwell
    assert ticks[-1][1] == "tracking"
    assert _transitions(ticks) == 2


def test_snapshot_says_stale_whenever_the_engine_holds_for_staleness(make_sim):
    s, ticks = _run(make_sim, _hiccups(0.7), 6.0)
    stale_ticks = [tk for tk in ticks if tk[5] == "pose_stale"]
    assert stale_ticks
    for *_, pose, _code, _ in stale_ticks:
        assert pose.stale and not pose.trusted and pose.reason.startswith("pose stale")
    for *_, pose, code, _ in ticks:
        if code is None:
            assert pose.trusted and not pose.stale


class StreamRig(TruthCameraRig):
    """Real-clock double: a thread publishes a pose every 20 ms, 30 ms after capture, unless
    ``paused`` is set."""

    def __init__(self, clock, paused: threading.Event):
        super().__init__("still", noise_mm=0.05)
        self.clock, self._sample, self._frames, self._lock = clock, None, [], threading.Lock()
        self._stop, self.paused = threading.Event(), paused

    def start(self):
        threading.Thread(target=self._run, daemon=True).start()

    def stop(self):
        self._stop.set()

    def _run(self):
        while not self._stop.is_set():
            if not self.paused.is_set():
                t = self.clock() - 0.03
                smp = self.estimate(self.capture(t))
                with self._lock:
                    self._sample = smp
                    self._frames.append(t)
            time.sleep(0.02)

    def poll_frames(self):
        with self._lock:
            out, self._frames = self._frames, []
        return out

    def latest_sample(self) -> PoseSample | None:
        return self._sample


def _wait_for(s, pred, timeout=30.0):
    """Until ``pred(snapshot)`` (polled every 10 ms), or False after the generous ``timeout`` s."""
    t_end = time.monotonic() + timeout
    while time.monotonic() < t_end:
        if pred(s.snapshot()):
            return True
        time.sleep(0.01)
    return False


@pytest.mark.serial  # the engine on the real clock: the serial lane (tests/conftest.py)
def test_start_tracking_waits_for_the_next_fresh_pose_on_a_real_clock(make_session):
    """A click that lands inside a short stale episode succeeds once fresh poses flow again; a
    stopped stream is refused with the reason (stale), after the bounded wait."""
    paused = threading.Event()
    # a generous wait: on a loaded test machine the double's own thread is late too
    s = make_session(clock="real", camera_factory=lambda *a: StreamRig(a[4].clock, paused),
                     robot_factory=lambda *a: FollowerRobotRig(), start_wait_s=5.0)
    s.start()
    plan_sample(s)
    assert s.start_camera().ok

    def wait_for(pred, timeout=30.0):
        return _wait_for(s, pred, timeout)

    assert wait_for(lambda snap: snap.pose is not None and snap.pose.trusted)
    r = s.arm("1234")
    assert r.ok, r.message
    paused.set()
    assert wait_for(lambda snap: snap.pose.stale)
    r = s.start_tracking()  # the stream is stopped: refused after the wait, saying why
    assert not r.ok and ("stale" in r.message or "camera stalled" in r.message or "camera late" in r.message)
    paused.clear()
    r = s.start_tracking()  # right away: inside the stale episode, but fresh poses flow again
    assert r.ok, r.message


def test_a_short_camera_freeze_resumes_only_after_the_dwell(make_sim):
    """A frozen camera is a gap in the fresh pose stream like a stale pose: a freeze of one frame
    (caught at its first bit-identical repeat, before any pose is stale) must not let the
    arm resume at the first new pose; it holds until poses have been fresh for resume_dwell_s
    again (a camera flickering between frozen and live must not start and stop the arm)."""
    rob = FollowerRobotRig()
    s = make_sim(clock="sim", camera="sim-points", trajectory="still", robot_factory=lambda *a: rob)
    plan_sample(s)
    assert s.start_camera().ok
    s.advance(0.5)
    assert s.arm("1234").ok and s.start_tracking().ok
    s.advance(1.0)
    assert rob.state == "tracking"
    ticks = []
    s.add_tick_listener(lambda t: ticks.append((t, rob.state)))
    t_fault = s.clock()
    assert s.inject_fault("camera-freeze").ok
    s.advance(1.2 / 30)  # the camera repeats one frame (measured: the arm resumed 64 ms after it)
    assert s.inject_fault("none").ok
    t_live = s.clock()
    s.advance(1.5)
    holding = [t for t, st in ticks if st == "holding"]
    assert holding, "the freeze must hold the arm"
    assert min(holding) <= t_fault + 2 / 30 + 0.01  # caught at the first repeated frame
    resumed = [t for t, st in ticks if st == "tracking" and t > min(holding)]
    assert resumed, "tracking resumes once the camera is live"
    # the first pose of the live camera comes >= one frame period after t_live; the dwell follows it
    assert min(resumed) >= t_live + 0.3, (t_live, min(resumed))
    assert all(st == "tracking" for t, st in ticks if t >= min(resumed))  # one hold, no flapping


class StartRecordingRobotRig(FollowerRobotRig):
    """Records the capture stamp of the newest target it had when each start arrived."""

    def __init__(self):
        super().__init__()
        self.start_stamps = []

    def start_tracking(self):
        self.start_stamps.append(self.stamp)
        return super().start_tracking()


@pytest.mark.serial  # the engine on the real clock: the serial lane (tests/conftest.py)
def test_start_tracking_is_sent_only_on_a_pose_that_just_arrived(make_session):
    """The arm's safety layer starts only on a target that *arrived* within its frame gap
    (``SafetyConfig.stale_s``, 0.1 s), a rule apart from the engine's capture-age limit: on a
    loaded machine a pose still young enough for the engine had often arrived too long ago for
    the arm, which refused ("no fresh valid target pose") beside "Pose: VALID". With the age
    limit out of the way (30 s), a pose that arrived longer ago than half the gap is refused
    with the reason, and a Start while poses flow again goes out on a newer pose."""
    from monotracker.engine.loop.robot import START_ARRIVAL_S
    from monotracker.robot.safety import SafetyConfig

    assert START_ARRIVAL_S == SafetyConfig().stale_s / 2
    paused = threading.Event()
    rob = StartRecordingRobotRig()
    s = make_session(clock="real", camera_factory=lambda *a: StreamRig(a[4].clock, paused),
                     robot_factory=lambda *a: rob, max_pose_age_s=30.0, freeze_after_s=30.0, start_wait_s=0.3)
    s.start()
    plan_sample(s)
    assert s.start_camera().ok
    assert _wait_for(s, lambda snap: snap.pose is not None and snap.pose.trusted)
    assert s.arm("1234").ok
    paused.set()
    loop = s._loop
    old = s.latest_pose().sample.t_capture
    # no pose arrives any more: wait until the newest arrived longer ago than the start allows
    assert _wait_for(s, lambda snap: loop.now() - loop._latest_arrival > START_ARRIVAL_S + 0.02)
    assert s.snapshot().pose.trusted  # the engine's own age limit still passes it
    r = s.start_tracking()
    assert not r.ok and "the arm needs poses at most 100 ms apart" in r.message, r.message
    assert rob.start_stamps == [] and rob.state == "armed"  # the arm was never asked
    s.config.start_wait_s = 30.0  # generous: the double's own thread is late on a loaded machine
    paused.clear()
    r = s.start_tracking()
    assert r.ok, r.message
    assert len(rob.start_stamps) == 1 and rob.start_stamps[0] > old
