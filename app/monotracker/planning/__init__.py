"""Before the patient is in the room: where to put the balls and the camera so that the error at
the target is small enough to trust (issue 31).

``plan_layout(problem, n_balls)`` suggests ball positions on the skin and a camera placement;
``predict(problem, T_ct_cam, centres)`` says what a layout and a camera pose will give (the
registration's own first-order model, with each ball's visibility). Build a problem with
``build_problem(HeadSurface.from_mesh(ct.head_surface(volume)), target, entry=..., existing=...)``
or field by field (:class:`PlanningProblem`). Units: CT LPS mm, px; camera poses ``T_ct_cam``.
"""
from typing import TYPE_CHECKING

from monotracker._lazy import lazy_exports

# imported now, not on first use: the function shares its module's name, and once anything imports
# the module monotracker.planning.visibility, the import system sets the package's attribute
# `visibility` to that module, so a lazy name would never be looked up (numpy only: cheap)
from monotracker.planning.visibility import Visibility, visibility

if TYPE_CHECKING:  # the names below, imported on first use (monotracker/_lazy.py: a fast CLI start)
    from monotracker.planning.candidates import Candidates, sample_candidates
    from monotracker.planning.camera_poses import CameraPose, camera_pose
    from monotracker.planning.defaults import build_problem, robot_keep_out
    from monotracker.planning.planner import LayoutPlan, plan_layout, rule_of_thumb_layout
    from monotracker.planning.prediction import Prediction, TargetError, predict
    from monotracker.planning.problem import (
        DEFAULT_NOISE_PX,
        BallRules,
        CameraSpace,
        Capsule,
        DrapeLine,
        HeadSurface,
        PlanningProblem,
    )

__all__ = [
    "DEFAULT_NOISE_PX", "BallRules", "CameraPose", "CameraSpace", "Candidates", "Capsule", "DrapeLine",
    "HeadSurface", "LayoutPlan", "PlanningProblem", "Prediction", "TargetError", "Visibility", "build_problem",
    "camera_pose", "plan_layout", "predict", "rule_of_thumb_layout", "sample_candidates", "robot_keep_out",
    "visibility",
]

__getattr__, __dir__ = lazy_exports(__name__, {
    "Candidates": "monotracker.planning.candidates",
    "sample_candidates": "monotracker.planning.candidates",
    "CameraPose": "monotracker.planning.camera_poses",
    "camera_pose": "monotracker.planning.camera_poses",
    "build_problem": "monotracker.planning.defaults",
    "robot_keep_out": "monotracker.planning.defaults",
    "LayoutPlan": "monotracker.planning.planner",
    "plan_layout": "monotracker.planning.planner",
    "rule_of_thumb_layout": "monotracker.planning.planner",
    "Prediction": "monotracker.planning.prediction",
    "TargetError": "monotracker.planning.prediction",
    "predict": "monotracker.planning.prediction",
    "DEFAULT_NOISE_PX": "monotracker.planning.problem",
    "BallRules": "monotracker.planning.problem",
    "CameraSpace": "monotracker.planning.problem",
    "Capsule": "monotracker.planning.problem",
    "DrapeLine": "monotracker.planning.problem",
    "HeadSurface": "monotracker.planning.problem",
    "PlanningProblem": "monotracker.planning.problem",
})
