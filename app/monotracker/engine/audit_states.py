"""The audit log's ``robot_state`` rows must tell one story: each row's ``from`` is the state the
row before it (in the same session) went ``to``, and a session's first row starts ``disarmed``
(every session starts disarmed, also after a crash).

A gap means a state change the log does not explain (a row lost, written out of order, or the
engine recording a state it polled rather than the transition that made it, issue 34).
:func:`state_rows_problem` is part of ``monotracker audit verify`` (``engine/audit.py``); it
reads, never writes.
"""

from __future__ import annotations

import json
import sqlite3

#: the state every session starts in (``engine/loop/robot.py``)
FIRST_STATE = "disarmed"


def state_rows_problem(db: sqlite3.Connection) -> tuple[int, str] | None:
    """``(row id, one line)`` for the first ``robot_state`` row that does not follow the one
    before it in its session, or None when they all do. Rows without ``from``/``to`` in their
    data are reported too (a state row that names no transition is no record)."""
    last: dict[str, tuple[int, str]] = {}  # session id -> (row id, state it went to)
    for rid, session_id, data in db.execute(
            "SELECT id, session_id, data FROM audit WHERE code = 'robot_state' ORDER BY id"):
        try:
            d = json.loads(data) if data else {}
            frm, to = d.get("from"), d.get("to")
        except (ValueError, AttributeError):
            frm = to = None
        if not isinstance(frm, str) or not isinstance(to, str):
            return rid, f"robot_state row {rid} does not say which transition it records (no from/to)"
        prev_id, prev_to = last.get(session_id, (None, FIRST_STATE))
        if frm != prev_to:
            where = (f"the previous state row ({prev_id}) went to {prev_to}" if prev_id is not None
                     else f"a session starts {FIRST_STATE}")
            return rid, f"robot_state row {rid} goes from {frm} but {where}: the state rows do not follow each other"
        last[session_id] = (rid, to)
    return None
