"""The papers' mathematics: pure numpy/scipy, no ROS imports.

Modules: rotation (angles, quaternions), parallel (Eqs 1-6), ptp (Eq 7), estimation (Eq 8),
navigation (Eqs 9-13), pushbroom (the rigorous scanner), intersection, epipolar (paper 2).
"""

from .epipolar import (
    EpipolarConstraint,
    Normalization,
    PlanarRectification,
    epipolar_from_affine,
    epipolar_from_points,
    invert_affine_2x3,
    normalize_pair,
    planar_rectification,
)
from .errors import (
    CrabAngleError,
    DegenerateGeometryError,
    DegeneratePointsError,
    GeometryError,
    TooFewPointsError,
)
from .estimation import AffineEstimate, check_point_set, estimate_affine
from .intersection import Intersection, SceneObservation, space_intersection
from .navigation import NavigationParameters, SceneFrame, parameters_from_navigation
from .parallel import (
    AffineInversion,
    AffineModel,
    ParallelProjection,
    affine_to_nonlinear,
    nonlinear_to_affine,
    paper_eqs_4_to_6,
)
from .ptp import ptp_forward, ptp_inverse, roll_from_rotation
from .pushbroom import ConstantMotion, LineCamera, PushbroomModel
from .rotation import (
    angles_from_rotation,
    quaternion_to_rotation,
    rotation_from_angles,
    rotation_to_quaternion,
)

__all__ = [
    "AffineEstimate",
    "AffineInversion",
    "AffineModel",
    "ConstantMotion",
    "CrabAngleError",
    "DegenerateGeometryError",
    "DegeneratePointsError",
    "EpipolarConstraint",
    "GeometryError",
    "Intersection",
    "LineCamera",
    "NavigationParameters",
    "Normalization",
    "ParallelProjection",
    "PlanarRectification",
    "PushbroomModel",
    "SceneFrame",
    "SceneObservation",
    "TooFewPointsError",
    "affine_to_nonlinear",
    "angles_from_rotation",
    "check_point_set",
    "epipolar_from_affine",
    "epipolar_from_points",
    "estimate_affine",
    "invert_affine_2x3",
    "nonlinear_to_affine",
    "normalize_pair",
    "paper_eqs_4_to_6",
    "parameters_from_navigation",
    "planar_rectification",
    "ptp_forward",
    "ptp_inverse",
    "quaternion_to_rotation",
    "roll_from_rotation",
    "rotation_from_angles",
    "rotation_to_quaternion",
    "space_intersection",
]
