"""Scripted scene events of the simulated camera (:mod:`.camera_sim`): occluders (hand and
instrument polygons sweeping over fiducials), stray green blobs and global lighting changes,
and :func:`random_events`, a reproducible mix of them. All positions are image pixels."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class Occluder:
    """A polygon (px, relative to its tip at (0, 0)) whose tip moves from ``start_px`` to
    ``end_px`` during [t_start, t_start + sweep_s], stays, and leaves at ``t_end``."""

    t_start: float
    t_end: float
    polygon: np.ndarray
    start_px: np.ndarray
    end_px: np.ndarray
    sweep_s: float = 0.5
    kind: str = "hand"

    def at(self, t: float) -> np.ndarray | None:
        if not (self.t_start <= t < self.t_end):
            return None
        f = np.clip((t - self.t_start) / self.sweep_s, 0.0, 1.0) if self.sweep_s > 0 else 1.0
        tip = (1 - f) * np.asarray(self.start_px) + f * np.asarray(self.end_px)
        return self.polygon + tip


@dataclass
class Stray:
    """A bright green blob at a fixed image position during [t_start, t_end)."""

    t_start: float
    t_end: float
    centre_px: tuple
    size_px: float
    shape: str = "round"      # "round" | "irregular" | "streak"
    seed: int = 0


@dataclass
class SceneEvents:
    occluders: list = field(default_factory=list)
    strays: list = field(default_factory=list)
    #: (t_s, gain) knots of the global lighting gain, linear in between (1.0 = nominal).
    lighting: list = field(default_factory=list)

    def gain(self, t: float) -> float:
        if not self.lighting:
            return 1.0
        ts, gs = zip(*self.lighting)
        return float(np.interp(t, ts, gs))


def _finger(width: float, length: float, angle: float) -> np.ndarray:
    """A finger/instrument polygon with its rounded tip at (0, 0) pointing along ``angle``."""
    a = np.linspace(-np.pi / 2, np.pi / 2, 9)
    tip = np.column_stack([-(width / 2) * np.cos(a) + width / 2, (width / 2) * np.sin(a)])
    body = np.array([[length, width / 2 + 8], [length, -width / 2 - 8]])
    poly = np.vstack([tip, body])
    c, s = np.cos(angle), np.sin(angle)
    # local +x points back along the finger; the finger enters from direction ``angle``
    return poly @ np.array([[c, s], [-s, c]])


def random_events(duration_s: float, fiducial_px: np.ndarray, image_size=(1280, 720), seed: int = 0,
                  occlusions: int = 3, strays: int = 3, lighting: bool = True) -> SceneEvents:
    """A reproducible mix of events over ``duration_s``: ``occlusions`` hand/instrument sweeps,
    each covering 1-2 fiducials for 1.5-3 s; ``strays`` green blobs (one round and fiducial-sized,
    the hardest case) for 2-6 s; a few lighting changes of +-25 %."""
    rng = np.random.default_rng(seed)
    ev = SceneEvents()
    w, h = image_size
    centre = fiducial_px.mean(axis=0)
    slots = np.linspace(0.15, 0.85, occlusions + 2)[1:-1] * duration_s if occlusions else []
    for k, ts in enumerate(slots):
        f = fiducial_px[rng.integers(len(fiducial_px))]
        out = f - centre
        out = out / (np.linalg.norm(out) + 1e-9)
        ang = np.arctan2(out[1], out[0]) + rng.uniform(-0.4, 0.4)
        direction = np.array([np.cos(ang), np.sin(ang)])
        kind = "hand" if k % 2 == 0 else "instrument"
        width = rng.uniform(55, 80) if kind == "hand" else rng.uniform(14, 22)
        poly = _finger(width, 900.0, ang)
        ev.occluders.append(Occluder(ts, ts + rng.uniform(1.5, 3.0), poly, f + 260 * direction,
                                     f - rng.uniform(5, 25) * direction, sweep_s=0.4, kind=kind))
    for k in range(strays):
        t0 = rng.uniform(0.05, 0.8) * duration_s
        shape = ("round", "irregular", "streak")[k % 3]
        if shape == "round":
            c = centre + rng.uniform(-1, 1, 2) * [250, 150]
        else:
            c = rng.uniform([80, 60], [w - 80, h - 60])
        ev.strays.append(Stray(t0, t0 + rng.uniform(2.0, 6.0), tuple(c), rng.uniform(7, 18), shape, seed + k))
    if lighting and duration_s > 4:
        knots = [(0.0, 1.0)]
        for t in np.sort(rng.uniform(2, duration_s, 3)):
            g = knots[-1][1]
            knots += [(t, g), (t + 0.5, float(rng.uniform(0.75, 1.25)))]
        ev.lighting = knots
    return ev
