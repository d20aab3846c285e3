"""The centre bias each detector leaves on physically rendered frames (issue 28 item 3).

:class:`~monotracker.registration.noise.CentreBias` values measured with
``benchmarks/camera_pbr.py --fit-bias`` on the **tuning** set of Mitsuba frames
(``monotracker.sim.pbr``; never on the held-out set), per detector. The pose tracker's trust
model takes the one of its detector (``TrackerConfig.centre_bias = "detector"``); a detector
may also carry its own (a ``centre_bias`` attribute), e.g. a retrained one. Re-measure and
update this table whenever a detector's centre method changes: a bias larger than written here
makes the predicted TRE over-confident.
"""

from __future__ import annotations

from monotracker.registration.noise import CentreBias

#: per detector (``name`` / ``centre_method``): measured on the tuning set, see each ``source``
CENTRE_BIAS = {
    # benchmarks/camera_pbr.py --fit-bias --detectors edge,learned --frames 8, 2026-11-26, tuning set
    # (30 Mitsuba scenes, 17 with >= 4 whole balls found): RMS over scenes, per coordinate,
    # ball 0.142 px / common 0.302 px (radius 8-9 px); by condition common 0.15 (clutter) to 0.43 px
    # (degraded)
    "edge": CentreBias(ball_per_radius=0.019, common_per_radius=0.046, prior_dof=6, noise_prior_px=0.15,
                       source="edge detector, 17 Mitsuba tuning scenes, 2026-11-26 (issue 28)"),
    # same run, 10 scenes: ball 0.179 px / common 0.319 px
    "learned": CentreBias(ball_per_radius=0.022, common_per_radius=0.0415, prior_dof=6, noise_prior_px=0.15,
                          source="learned detector, 10 Mitsuba tuning scenes, 2026-11-26 (issue 28)"),
    # benchmarks/camera_pbr.py --fit-bias --detectors refined,edge --frames 8, 2026-11-30, tuning set (26
    # Mitsuba scenes, 18 with >= 4 whole balls found): the edge detector with the learned centre
    # refiner (static/centre_refiner.onnx, trained on the train split only); RMS over scenes, per
    # coordinate, ball 0.090 px / common 0.113 px (radius 8-9 px); by condition common 0.052 (clutter)
    # to 0.166 px (degraded). The edge detector in the same run: ball 0.151 / common 0.270 px
    "refined": CentreBias(ball_per_radius=0.0137, common_per_radius=0.0261, prior_dof=6, noise_prior_px=0.15,
                          source="edge detector + centre refiner, 18 Mitsuba tuning scenes, 2026-11-30 (issue 28)"),
}
#: a detector this table does not know (the chroma centroid included: not measured): the largest
#: of the measured ones in each part
UNKNOWN = CentreBias(ball_per_radius=max(b.ball_per_radius for b in CENTRE_BIAS.values()),
                     common_per_radius=max(b.common_per_radius for b in CENTRE_BIAS.values()),
                     prior_dof=6, noise_prior_px=0.15, source="unmeasured detector: the largest measured bias")


def detector_key(detector) -> str:
    """``edge``, ``refined`` (the edge detector with a centre refiner), ``chroma`` or ``learned``
    for our detectors; the detector's ``name`` else."""
    name = str(getattr(detector, "name", ""))
    if name == "learned":
        return "learned"
    if getattr(detector, "refiner", None) is not None:
        return "refined"
    method = getattr(detector, "centre_method", None)
    return str(method) if method in ("edge", "chroma") else name


def centre_bias_of(detector) -> CentreBias:
    """The bias the trust model must cover for ``detector``: its own ``centre_bias`` attribute,
    else this table's entry, else :data:`UNKNOWN`. A wrapper (``.det`` / ``.detector``) is
    looked through."""
    inner = detector
    for _ in range(3):
        own = getattr(inner, "centre_bias", None)
        if isinstance(own, CentreBias):
            return own
        key = detector_key(inner)
        if key in CENTRE_BIAS:
            return CENTRE_BIAS[key]
        inner = getattr(inner, "det", None) or getattr(inner, "detector", None)
        if inner is None:
            break
    return UNKNOWN
