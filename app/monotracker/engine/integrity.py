"""What lets a saved session prove it was not changed behind the app's back.

Three layers (``docs/integrity.md`` says what each protects against, and what none does):

* **Content hashes.** :func:`stamp_plan_dict` adds ``integrity.plan_sha256`` to a plan's dict:
  SHA-256 of its canonical JSON (sorted keys, no whitespace) without the stamps. It is not keyed:
  it tells an accidental edit or a damaged file, not a deliberate one (anyone can recompute it).
  :func:`content_sha256` hashes a CT file or series and a calibration file; the plan records
  them and a restart compares.
* **This machine's key.** :class:`IntegrityKey`: 32 random bytes in ``paths.key_dir()``
  (``$MONOTRACKER_KEY_DIR``, else ``~/.config/monotracker``; outside every session folder; file
  mode 0600), created on first use. HMAC-SHA256 with it stamps the saved plan
  (``integrity.plan_mac``), every audit row and every spilled audit line, and the audit log's
  *anchor*: its newest row's id and hash, kept in the key folder (:meth:`IntegrityKey.write_anchor`),
  so rows deleted from the end, a rewritten chain or an erased file no longer pass as intact.
* **The audit chain.** Each plan save first writes a ``plan_saved`` row (the plan, its digest and
  the digest of the plan it replaces) durably into the audit log; at start-up the plan on disk
  must be the one the log last recorded (:func:`judge_saved_plan`), else the app's own last plan
  is restored from the log and the edited file is kept aside, with the differences named
  (:func:`describe_plan_changes`).
"""

from __future__ import annotations

import hashlib
import hmac
import json
import logging
import os
import secrets
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

log = logging.getLogger(__name__)

KEY_FILE = "integrity.key"
ANCHOR_DIR = "anchors"
KEY_BYTES = 32
#: the stamps a plan's content digest and MAC leave out (they are computed over the rest)
STAMPS = ("plan_sha256", "plan_mac")

_CHUNK = 1 << 20


def _canonical(d: dict) -> bytes:
    return json.dumps(d, sort_keys=True, separators=(",", ":"), allow_nan=True).encode("utf-8")


def _unstamped(d: dict) -> dict:
    body = dict(d)
    integ = body.get("integrity")
    if isinstance(integ, dict):
        body["integrity"] = {k: v for k, v in integ.items() if k not in STAMPS}
    return body


def plan_content_sha256(d: dict) -> str:
    """SHA-256 (hex) of a plan dict without its stamps (``integrity.plan_sha256`` / ``plan_mac``)."""
    return hashlib.sha256(_canonical(_unstamped(d))).hexdigest()


def plan_mac(d: dict, key: "IntegrityKey | None") -> str | None:
    """HMAC-SHA256 (hex) of the plan's unstamped content with this machine's key; None without one."""
    return None if key is None else key.mac(_canonical(_unstamped(d)))


def stamp_plan_mac(d: dict, key: "IntegrityKey | None") -> dict:
    """``d`` (a stamped plan dict) with ``integrity.plan_mac`` set when a key is available."""
    mac = plan_mac(d, key)
    if mac is not None:
        d.setdefault("integrity", {})["plan_mac"] = mac
    return d


_MACHINE_KEYS: dict = {}


def machine_key() -> "IntegrityKey | None":
    """This machine's key (``paths.key_dir()``) when one exists, else None; never creates one
    (the session's audit log does, at start). Cached once found."""
    from monotracker.paths import key_dir

    folder = key_dir()
    k = _MACHINE_KEYS.get(folder)
    if k is None:
        k = IntegrityKey(folder, create=False)
        if not k.available:
            return None
        _MACHINE_KEYS[folder] = k
    return k


def stamp_plan_dict(d: dict) -> dict:
    """``d`` with ``integrity.plan_sha256`` set to its content hash and, when this machine has
    an integrity key (:func:`machine_key`), ``integrity.plan_mac`` set to its MAC (``d`` is
    modified and returned). Every plan file the app writes is stamped here."""
    integ = dict(d.get("integrity") or {})
    for k in STAMPS:
        integ.pop(k, None)
    d["integrity"] = integ
    integ["plan_sha256"] = plan_content_sha256(d)
    return stamp_plan_mac(d, machine_key())


def plan_stamp_problem(d: dict) -> str | None:
    """None when the parsed plan file carries a content hash that matches; else one line."""
    integ = d.get("integrity") if isinstance(d, dict) else None
    rec = integ.get("plan_sha256") if isinstance(integ, dict) else None
    if not isinstance(rec, str):
        return "the plan file carries no content hash (written by an older version or by hand)"
    if rec != plan_content_sha256(d):
        return "the plan file was changed outside the app (its content hash does not match)"
    return None


def content_sha256(path) -> str:
    """SHA-256 (hex) of a file's bytes, or of a folder's regular files (names relative to the
    folder and contents, sorted by name). Raises ``OSError`` when it cannot be read."""
    p = Path(path)
    h = hashlib.sha256()
    if p.is_dir():
        files = sorted(q for q in p.rglob("*") if q.is_file())
        for q in files:
            h.update(str(q.relative_to(p)).encode("utf-8") + b"\0")
            _feed(h, q)
            h.update(b"\0")
    else:
        _feed(h, p)
    return h.hexdigest()


def _feed(h, path: Path) -> None:
    with open(path, "rb") as fh:
        while True:
            b = fh.read(_CHUNK)
            if not b:
                return
            h.update(b)


def compare_content(path, recorded: str | None, what: str) -> str | None:
    """None when ``path`` still hashes to ``recorded`` (or nothing was recorded); else one line."""
    if not recorded:
        return None
    if path is None:
        return f"the plan's {what} path is not recorded"
    try:
        now = content_sha256(path)
    except OSError as exc:
        return f"the plan's {what} {path} cannot be read ({exc.strerror or exc})"
    if now != recorded:
        return f"the plan's {what} {path} changed since the plan was made (content hash differs)"
    return None


# ---------------------------------------------------------------------------------------------
# this machine's key, and the audit logs' anchors
class IntegrityKey:
    """This machine's integrity key (see the module docstring).

    ``folder``: where the key and the anchors live (None: ``paths.key_dir()``). ``create``: make a
    new key when there is none (the app does; ``audit verify`` does not). :attr:`problem` says in
    one line why there is no key (unreadable, damaged, cannot be created); :meth:`mac` then
    returns None and callers fall back to what the audit chain alone can show."""

    def __init__(self, folder=None, create: bool = True):
        from monotracker.paths import key_dir

        self.folder = Path(folder) if folder is not None else key_dir()
        self.path = self.folder / KEY_FILE
        self.problem: str | None = None
        self._key = self._load(create)

    @property
    def available(self) -> bool:
        return self._key is not None

    def _load(self, create: bool) -> bytes | None:
        try:
            raw = self.path.read_bytes()
        except FileNotFoundError:
            if not create:
                self.problem = f"no integrity key at {self.path}"
                return None
            return self._create()
        except OSError as exc:
            self.problem = f"integrity key {self.path} cannot be read ({exc.strerror or exc})"
            return None
        if len(raw) != KEY_BYTES:
            self.problem = f"integrity key {self.path} is damaged ({len(raw)} bytes, not {KEY_BYTES})"
            return None
        return raw

    def _create(self) -> bytes | None:
        """A new random key, published atomically with ``os.link`` (a second process starting at
        the same time reads the first one's key instead of making its own)."""
        tmp = self.folder / f".{KEY_FILE}.{os.getpid()}.{secrets.token_hex(4)}"
        try:
            self.folder.mkdir(mode=0o700, parents=True, exist_ok=True)
            fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
            try:
                os.write(fd, secrets.token_bytes(KEY_BYTES))
                os.fsync(fd)
            finally:
                os.close(fd)
            try:
                os.link(tmp, self.path)
            except FileExistsError:
                pass  # another process was first: use its key
            raw = self.path.read_bytes()
        except OSError as exc:
            self.problem = f"cannot create the integrity key in {self.folder} ({exc.strerror or exc})"
            return None
        finally:
            try:
                tmp.unlink()
            except OSError:
                pass
        if len(raw) != KEY_BYTES:
            self.problem = f"integrity key {self.path} is damaged ({len(raw)} bytes, not {KEY_BYTES})"
            return None
        log.info("integrity key created at %s", self.path)
        return raw

    def mac(self, data) -> str | None:
        """HMAC-SHA256 (hex) of ``data`` (bytes or str), or None without a key."""
        if self._key is None:
            return None
        if isinstance(data, str):
            data = data.encode("utf-8")
        return hmac.new(self._key, data, hashlib.sha256).hexdigest()

    def check(self, data, mac) -> bool | None:
        """True / False whether ``mac`` is ``data``'s MAC; None without a key."""
        want = self.mac(data)
        if want is None:
            return None
        return isinstance(mac, str) and hmac.compare_digest(want, mac)

    # ------------------------------------------------------------------ anchors
    def anchor_path(self, audit_path) -> Path:
        """The anchor file of the audit database at ``audit_path`` (named by its absolute path)."""
        name = hashlib.sha256(str(Path(audit_path).resolve()).encode("utf-8")).hexdigest()[:24]
        return self.folder / ANCHOR_DIR / f"{name}.json"

    def write_anchor(self, audit_path, log_id: str, last_id: int, last_hash: str) -> None:
        """Record the newest row (``last_id``, ``last_hash``) of the log whose first row's hash is
        ``log_id``; atomic and durable. Raises ``OSError``; does nothing without a key."""
        if self._key is None:
            return
        from monotracker.engine.persistence import atomic_write_json

        body = {"audit": str(Path(audit_path).resolve()), "log_id": log_id, "last_id": int(last_id),
                "last_hash": last_hash, "t_unix": time.time()}
        body["mac"] = self.mac(_canonical(body))
        path = self.anchor_path(audit_path)
        path.parent.mkdir(mode=0o700, parents=True, exist_ok=True)
        atomic_write_json(path, body)

    def read_anchor(self, audit_path, log_id: str | None = None) -> tuple[dict | None, str | None]:
        """``(anchor, None)``, ``(None, None)`` when there is none, or ``(None, why)`` when one is
        there but its MAC does not verify (changed) or it cannot be read. Looked up by the
        database's path, then (a moved folder) by ``log_id``."""
        if self._key is None:
            return None, None
        cands = [self.anchor_path(audit_path)]
        if log_id:
            try:
                cands += sorted((self.folder / ANCHOR_DIR).glob("*.json"))
            except OSError:
                pass
        for i, path in enumerate(cands):
            try:
                d = json.loads(path.read_text(encoding="utf-8"))
            except FileNotFoundError:
                continue
            except (OSError, ValueError) as exc:
                if i == 0:
                    return None, f"the audit anchor {path} cannot be read ({exc})"
                continue
            if not isinstance(d, dict):
                if i == 0:
                    return None, f"the audit anchor {path} is damaged"
                continue
            if i > 0 and d.get("log_id") != log_id:
                continue
            body = {k: v for k, v in d.items() if k != "mac"}
            if not self.check(_canonical(body), d.get("mac")):
                return None, f"the audit anchor {path} was changed (its MAC does not verify)"
            return d, None
        return None, None


# ---------------------------------------------------------------------------------------------
# what changed between two plans, in the operator's words
def _vec(v):
    try:
        a = np.asarray(v, float)
    except (TypeError, ValueError):
        return None
    return a if a.size and np.all(np.isfinite(a)) else None


def _moved(a, b) -> float | None:
    a, b = _vec(a), _vec(b)
    if a is None or b is None or a.shape != b.shape:
        return None
    return float(np.linalg.norm(a - b))


def describe_plan_changes(old: dict, new: dict) -> list[str]:
    """What ``new`` changes in ``old`` (two plan dicts), one short phrase each: points moved (mm),
    the hand-eye rotated (deg) / shifted (mm), fiducials moved, added, removed or re-labelled,
    and any other field by name. Empty when they agree (stamps and revision aside)."""
    out: list[str] = []
    for name, label in (("target_lps_mm", "target"), ("entry_lps_mm", "entry")):
        a, b = old.get(name), new.get(name)
        if a == b:
            continue
        d = _moved(a, b)
        out.append(f"{label} moved {d:.1f} mm" if d is not None else f"{label} changed")
    Ta, Tb = _vec(old.get("T_base_cam_mm")), _vec(new.get("T_base_cam_mm"))
    if old.get("T_base_cam_mm") != new.get("T_base_cam_mm"):
        if Ta is not None and Tb is not None and Ta.shape == Tb.shape == (4, 4):
            R = Ta[:3, :3].T @ Tb[:3, :3]
            ang = float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1.0, 1.0))))
            shift = float(np.linalg.norm(Ta[:3, 3] - Tb[:3, 3]))
            parts = ([f"rotated {ang:.1f} deg"] if ang >= 0.05 else []) + ([f"shifted {shift:.1f} mm"] if shift >= 0.05 else [])
            out.append("hand-eye " + (", ".join(parts) if parts else "changed (less than 0.05 deg / 0.05 mm)"))
        else:
            out.append("hand-eye changed")
    fa = {f.get("id"): f for f in old.get("fiducials") or [] if isinstance(f, dict)}
    fb = {f.get("id"): f for f in new.get("fiducials") or [] if isinstance(f, dict)}
    for fid in sorted(set(fa) | set(fb), key=str):
        a, b = fa.get(fid), fb.get(fid)
        if a is None:
            out.append(f"fiducial {fid} added")
        elif b is None:
            out.append(f"fiducial {fid} removed")
        elif a != b:
            d = _moved(a.get("centre_lps_mm"), b.get("centre_lps_mm"))
            if d:
                out.append(f"fiducial {fid} moved {d:.1f} mm")
            others = sorted(k for k in set(a) | set(b) if k != "centre_lps_mm" and a.get(k) != b.get(k))
            if others:
                out.append(f"fiducial {fid} {', '.join(others)} changed")
    skip = {"target_lps_mm", "entry_lps_mm", "T_base_cam_mm", "fiducials", "integrity", "revision"}
    for k in sorted((set(old) | set(new)) - skip):
        if old.get(k) != new.get(k):
            out.append(f"{k} changed")
    ia = {k: v for k, v in (old.get("integrity") or {}).items() if k not in STAMPS}
    ib = {k: v for k, v in (new.get("integrity") or {}).items() if k not in STAMPS}
    if ia != ib:
        out.append("recorded CT/calibration hashes changed")
    return out


def summarise_changes(changes: list[str], most: int = 4) -> str:
    """The first ``most`` phrases, and how many more."""
    if not changes:
        return "no field differs"
    more = len(changes) - most
    return "; ".join(changes[:most]) + (f"; and {more} more" if more > 0 else "")


# ---------------------------------------------------------------------------------------------
# is the plan on disk the app's own?
@dataclass(frozen=True)
class PlanVerdict:
    """What :func:`judge_saved_plan` found. ``ok``: the file is the plan the app saved last.
    ``interrupted``: it is the plan *before* the last recorded save (a save cut short between its
    audit row and the file: ``kill -9``, a full disk); the file is used. Otherwise ``how`` says how
    the change was seen (one phrase), ``changes`` what differs from the app's last plan (phrases
    of :func:`describe_plan_changes`), ``app_plan`` the app's last plan to restore (a plan dict
    from the audit chain) or None when it cannot be reconstructed."""

    ok: bool
    interrupted: bool = False
    how: str = ""
    changes: tuple = ()
    app_plan: dict | None = None


def judge_saved_plan(raw: dict, last_saved: dict | None, key: "IntegrityKey | None") -> PlanVerdict | None:
    """Is ``raw`` (the parsed ``plan.json``) the plan this app saved last?

    ``last_saved``: the ``data`` of the audit chain's newest ``plan_saved`` row that verifies
    (``{"plan", "plan_sha256", "previous_sha256", ...}``), or None; ``key``: this machine's key.
    The audit chain decides when it holds a plan: the file's content digest must be its last one
    (or, after a save cut short, the one before, with this machine's MAC). Without such a row the
    file's MAC decides. None when neither can (no row, and no MAC or no key: a file of an older
    version; the caller falls back to the unkeyed content hash)."""
    sha = plan_content_sha256(raw)
    integ = raw.get("integrity") if isinstance(raw.get("integrity"), dict) else {}
    mac = integ.get("plan_mac")
    mac_ok = None  # None: no MAC to check (a file of an older version, or no key here)
    if key is not None and key.available and "plan_mac" in integ:
        mac_ok = isinstance(mac, str) and bool(key.check(_canonical(_unstamped(raw)), mac))
    if isinstance(last_saved, dict) and isinstance(last_saved.get("plan"), dict):
        if sha == last_saved.get("plan_sha256"):
            return PlanVerdict(True)
        if sha == last_saved.get("previous_sha256") and mac_ok:
            return PlanVerdict(True, interrupted=True)
        app = last_saved["plan"]
        how = "it is not the plan the audit log recorded last"
        if mac_ok is False:
            how = "its MAC does not verify and it is not the plan the audit log recorded last"
        return PlanVerdict(False, how=how, changes=tuple(describe_plan_changes(app, raw)), app_plan=app)
    if mac_ok is None:
        return None
    if mac_ok:
        return PlanVerdict(True)
    return PlanVerdict(False, how="its MAC does not verify (not written by this app with this machine's key)",
                       changes=())
