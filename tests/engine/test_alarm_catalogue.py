"""One alarm catalogue: every code that reaches the alarm board has a row (level, priority, flags),
and a code without one is shown as an alarm, never hidden as a rate-limited warning.

The codes are collected from the source (an AST walk, not a list kept by hand): what the engine
sets on the board or holds the arm for, what vision's pose tracker gives an invalid estimate and
what the trust verdict calls its refusals."""

from __future__ import annotations

import ast
import logging
from pathlib import Path

import monotracker
from monotracker.engine import alarms
from monotracker.engine.alarms import CATALOGUE, VERDICT_CODES, AlarmBoard

PKG = Path(monotracker.__file__).parent
#: calls whose first argument is a code that reaches the board
BOARD_CALLS = {"_hold", "hold", "_persistent_alarm", "persistent", "_set_pose_alarm", "set_condition"}


def _receiver(node: ast.Call) -> str:
    f = node.func
    return ast.unparse(f.value) if isinstance(f, ast.Attribute) else ""


def _first_str(node: ast.Call) -> str | None:
    if node.args and isinstance(node.args[0], ast.Constant) and isinstance(node.args[0].value, str):
        return node.args[0].value
    return None


def board_codes(source: str) -> set[str]:
    """Codes set on an alarm board or raised as a hold in ``source``."""
    out = set()
    for node in ast.walk(ast.parse(source)):
        if not isinstance(node, ast.Call) or not isinstance(node.func, ast.Attribute):
            continue
        name, code = node.func.attr, _first_str(node)
        if code is None:
            continue
        if name in BOARD_CALLS or (name == "set" and _receiver(node).endswith(("board", "alarms"))):
            out.add(code)
    return out


def estimator_codes(source: str) -> set[str]:
    """String constants assigned to ``code`` (names, tuple unpacking, ``a if c else b``), and the
    code argument of the pose tracker's ``_invalid``."""
    out = set()
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Assign):
            for target in node.targets:
                names = target.elts if isinstance(target, ast.Tuple) else [target]
                values = node.value.elts if isinstance(node.value, ast.Tuple) else [node.value]
                for n, v in zip(names, values):
                    if isinstance(n, ast.Name) and n.id == "code":
                        options = [v.body, v.orelse] if isinstance(v, ast.IfExp) else [v]
                        out |= {o.value for o in options if isinstance(o, ast.Constant) and o.value}
        elif isinstance(node, ast.Call) and getattr(node.func, "attr", "") == "_invalid" and len(node.args) > 2:
            arg = node.args[2]
            if isinstance(arg, ast.Constant) and isinstance(arg.value, str):
                out.add(arg.value)
    return out


def verdict_codes(source: str) -> set[str]:
    """The codes of the trust verdicts the gate returns (second argument of ``GateVerdict``)."""
    out = set()
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Call) and getattr(node.func, "id", "") == "GateVerdict" and len(node.args) > 1:
            arg = node.args[1]
            if isinstance(arg, ast.Constant) and isinstance(arg.value, str):
                out.add(arg.value)
    return out


def _all_sources():
    return [(p, p.read_text()) for p in PKG.rglob("*.py")]


def test_every_code_that_reaches_the_board_has_a_row():
    found = {}
    for path, src in _all_sources():
        for code in board_codes(src):
            found.setdefault(code, path.relative_to(PKG))
    assert len(found) >= 10, found  # the walk sees the engine's holds and board sets
    missing = {c: str(p) for c, p in found.items() if c not in CATALOGUE}
    assert not missing, f"codes reaching the alarm board without a row in alarms.CATALOGUE: {missing}"


def test_every_refusal_of_the_estimator_and_the_verdict_has_a_row():
    from monotracker.vision.pose_tracker import CAMERA_CODES

    # the tracker's own refusals and its trust models' (frame_trust, pooled_trust)
    tracker_src = "\n".join((PKG / "vision" / name).read_text()
                            for name in ("pose_tracker.py", "frame_trust.py", "pooled_trust.py"))
    codes = estimator_codes(tracker_src) | set(CAMERA_CODES.values())
    assert {"occlusion", "pose_lost", "tre_limit", "frame_size"} <= codes, codes
    gate_src = "\n".join(src for p, src in _all_sources() if "GateVerdict(" in src)
    verdicts = (verdict_codes(gate_src) | estimator_codes(gate_src)) - {"ok"}
    assert {"fre", "jump", "acquiring", "estimator"} <= verdicts, verdicts
    held = codes | {VERDICT_CODES.get(v, v) for v in verdicts}
    missing = sorted(c for c in held if c not in CATALOGUE)
    assert not missing, f"refusal codes without a row in alarms.CATALOGUE: {missing}"
    assert all(CATALOGUE[c].holds_arm for c in held), [c for c in held if not CATALOGUE[c].holds_arm]


def test_the_walk_catches_a_code_without_a_row():
    planted = 'def f(self, now):\n    self.s._alarm_board.set("no_such_condition", "x", now)\n' \
              '    self._hold("another_unlisted", "why")\n'
    assert board_codes(planted) == {"no_such_condition", "another_unlisted"}


def test_flags_live_in_the_rows():
    assert set(alarms.POSE_CODES) == {c for c, k in CATALOGUE.items() if k.holds_arm}
    assert set(alarms.FRESHNESS_CODES) == {"pose_stale", "camera_freeze", "camera_late", "camera_stalled",
                                           "pipeline_overloaded"}
    assert set(alarms.CAMERA_SETUP_CODES) == {"camera_uncalibrated", "camera_compressed", "camera_short_lens",
                                              "colour_clash"}
    assert VERDICT_CODES == {"estimator": "pose_lost", "fre": "bad_pose", "jump": "pose_jump"}
    assert all(k.level in ("alarm", "warning", "info") for k in CATALOGUE.values())


def test_an_unlisted_code_is_shown_as_an_alarm_under_the_estop_and_logged(caplog):
    b = AlarmBoard()
    with caplog.at_level(logging.ERROR, logger="monotracker.engine.alarms"):
        assert b.set("brand_new_condition", "something nobody catalogued", 1.0)
        assert b.set("brand_new_condition_2", "again", 1.0)
    b.set("estop", "e-stop", 2.0)
    b.set("occlusion", "3 fiducials", 2.0)
    active = b.active(2.0)
    assert [a.code for a in active][:2] == ["estop", "brand_new_condition"]
    unknown = active[1]
    assert unknown.level == "alarm"
    assert "brand_new_condition" in caplog.text and "no row" in caplog.text
    # reported every episode, not rate-limited as a technical condition
    b.clear("brand_new_condition", 3.0)
    b.active(3.0)
    assert b.set("brand_new_condition", "back", 3.5)


def test_alerts_of_a_catalogued_code_carry_its_rows_level(make_session):
    s = make_session(clock="sim")
    ev = s.alert("warning", "ct_failed", "CT could not be used")
    assert ev.level == CATALOGUE["ct_failed"].level == "alarm"
    ev = s.alert("warning", "resumed", "history only: no row, the caller's level")
    assert ev.level == "warning"


def test_a_pose_the_scene_keeps_from_being_trusted_says_what_to_do():
    """Issue 28: on realistic frames the pose is refused often; the refusals the team can act on
    (too few balls, too large an error, balls on a line, a mismatch) carry a remedy from their row,
    and the alarm list shows it; a condition whose message says it all shows none."""
    from monotracker.ui.status import alarms_html

    scene = ("occlusion", "tre_limit", "weak_geometry", "pose_lost", "bad_pose", "pose_jump", "colour_clash")
    assert all(CATALOGUE[c].remedy for c in scene), [c for c in scene if not CATALOGUE[c].remedy]
    assert not CATALOGUE["estop"].remedy
    b = AlarmBoard()
    b.set("estop", "e-stop pressed", 1.0)
    b.set("tre_limit", "predicted error at the target 1.4 mm", 1.0)
    active = {a.code: a for a in b.active(1.5)}
    assert active["tre_limit"].remedy == CATALOGUE["tre_limit"].remedy and active["estop"].remedy == ""
    html = alarms_html(type("Snap", (), {"alarms": tuple(active.values())})())
    assert html.count("What to do:") == 1 and "bring the camera nearer" in html
