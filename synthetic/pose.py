"""Posing a subject: linear-blend skinning of the rest mesh over a ten-bone skeleton.

The skeleton (torso, head, upper arms, forearms with hands, thighs, shins with feet) hangs from joint
positions found in the MakeHuman mesh's `joint-*` helper groups. Each vertex takes its bone from the
nearest bone capsule (segment and radius); the one-hot weights are then averaged over mesh neighbours a
number of times (scaled to the mesh resolution), so weights blend over a few centimetres along the
surface round every joint (no tearing at shoulders, elbows, hips, knees, neck) and never leak between
parts that only touch in space (an arm and the torso below the armpit are not connected). A pose is a
dict of joint angles in degrees (`POSE_RANGES_DEG`); `pose_variation` scales the uniform draw, so 0 is
the rest pose exactly. Linear blend skinning loses some volume on the inside of strongly bent elbows and
knees (a few triangles shrink to a few percent of their area); nothing tears or turns NaN.

Everything here is arrays in, arrays out.
"""
from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

BONES = ("torso", "head", "l_upper_arm", "l_forearm", "r_upper_arm", "r_forearm",
         "l_thigh", "l_shin", "r_thigh", "r_shin")
"""Bone names; a bone rotates about its joint (`Skeleton.joints[bone]`) relative to its parent."""
PARENTS = {"torso": None, "head": "torso", "l_upper_arm": "torso", "l_forearm": "l_upper_arm",
           "r_upper_arm": "torso", "r_forearm": "r_upper_arm", "l_thigh": "torso", "l_shin": "l_thigh",
           "r_thigh": "torso", "r_shin": "r_thigh"}

MAKEHUMAN_JOINTS = {
    "pelvis": "joint-pelvis", "chest": "joint-spine-1", "neck": "joint-neck", "head_top": "joint-head-2",
    "l_shoulder": "joint-l-shoulder", "l_elbow": "joint-l-elbow", "l_wrist": "joint-l-hand",
    "l_fingertip": "joint-l-finger-3-4", "l_hip": "joint-l-upper-leg", "l_knee": "joint-l-knee",
    "l_ankle": "joint-l-ankle", "l_toe": "joint-l-foot-2",
    "r_shoulder": "joint-r-shoulder", "r_elbow": "joint-r-elbow", "r_wrist": "joint-r-hand",
    "r_fingertip": "joint-r-finger-3-4", "r_hip": "joint-r-upper-leg", "r_knee": "joint-r-knee",
    "r_ankle": "joint-r-ankle", "r_toe": "joint-r-foot-2"}
"""Skeleton landmark -> MakeHuman helper group whose vertex centroid is the landmark. `l_` is the
subject's left (+x: the subject faces +z)."""

POSE_RANGES_DEG = {
    "neck_turn": (-40.0, 40.0),        # head about +y (look left / right)
    "neck_bend": (-15.0, 25.0),        # head about +x (+ = nod forward)
    "neck_tilt": (-12.0, 12.0),        # head about +z (ear to shoulder)
    "l_shoulder_raise": (-20.0, 40.0),  # arm in the frontal plane (+ = away from the body; rest: A-pose)
    "l_shoulder_swing": (-25.0, 50.0),  # arm about x (+ = forward)
    "l_elbow_bend": (-20.0, 50.0),     # forearm about the elbow axis (+ = flexed; rest is half bent)
    "r_shoulder_raise": (-20.0, 40.0),
    "r_shoulder_swing": (-25.0, 50.0),
    "r_elbow_bend": (-20.0, 50.0),
    "l_hip_swing": (-20.0, 35.0),      # thigh about x (+ = forward)
    "l_hip_spread": (-3.0, 15.0),      # thigh in the frontal plane (+ = outward)
    "l_knee_bend": (0.0, 60.0),        # shin about x (+ = foot backward)
    "r_hip_swing": (-20.0, 35.0),
    "r_hip_spread": (-3.0, 15.0),
    "r_knee_bend": (0.0, 60.0),
}
"""Joint angle ranges at pose_variation 1, degrees. An action's angle is pose_variation times a uniform
draw in its range. The ranges keep the limbs off the body: arms raised at most to horizontal (A-pose rest
at ~40 degrees from vertical), lowered by at most 20 degrees (hands stay clear of the hips), forearms bend
in the plane of the upper arm and the forward direction (hands never cross to the midline), thighs
spread inward by at most 3 degrees."""

CHAINS = {"head": ("neck_turn", "neck_bend", "neck_tilt"),
          "l_arm": ("l_shoulder_raise", "l_shoulder_swing", "l_elbow_bend"),
          "r_arm": ("r_shoulder_raise", "r_shoulder_swing", "r_elbow_bend"),
          "l_leg": ("l_hip_swing", "l_hip_spread", "l_knee_bend"),
          "r_leg": ("r_hip_swing", "r_hip_spread", "r_knee_bend")}
"""The joint angles of each limb chain: a chain's angles move only the vertices skinned to its bones."""
CHAIN_BONES = {"head": ("head",), "l_arm": ("l_upper_arm", "l_forearm"), "r_arm": ("r_upper_arm", "r_forearm"),
               "l_leg": ("l_thigh", "l_shin"), "r_leg": ("r_thigh", "r_shin")}

BLEND_M = 0.025
"""Standard deviation of the skinning weights' blend across a joint boundary, metres, along the surface."""


@dataclass(frozen=True)
class Skeleton:
    """Joints (rest positions, metres, in the subject's rest frame) and per-vertex skinning weights.

    joints: bone name -> (3,) position of the joint it rotates about; landmarks: landmark name -> (3,);
    weights: (V, len(BONES)) float64, rows sum to 1.
    """
    joints: dict[str, np.ndarray]
    landmarks: dict[str, np.ndarray]
    weights: np.ndarray


def bone_joints(landmarks: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Joint position of every bone from skeleton landmarks (MAKEHUMAN_JOINTS keys)."""
    joints = {"torso": landmarks["pelvis"], "head": landmarks["neck"]}
    for side in ("l", "r"):
        joints[f"{side}_upper_arm"] = landmarks[f"{side}_shoulder"]
        joints[f"{side}_forearm"] = landmarks[f"{side}_elbow"]
        joints[f"{side}_thigh"] = landmarks[f"{side}_hip"]
        joints[f"{side}_shin"] = landmarks[f"{side}_knee"]
    return {name: np.asarray(joints[name], np.float64) for name in BONES}


def bone_capsules(landmarks: dict[str, np.ndarray]) -> list[tuple[str, np.ndarray, np.ndarray, float]]:
    """Capsules (bone, a (3,), b (3,), radius m) whose nearest one labels a vertex (adult proportions)."""
    lm = {k: np.asarray(v, np.float64) for k, v in landmarks.items()}
    capsules = [("torso", lm["pelvis"], lm["chest"], 0.13), ("head", lm["neck"], lm["head_top"], 0.07)]
    for side in ("l", "r"):
        capsules += [
            ("torso", lm["chest"], lm[f"{side}_shoulder"], 0.06),
            (f"{side}_upper_arm", lm[f"{side}_shoulder"], lm[f"{side}_elbow"], 0.045),
            (f"{side}_forearm", lm[f"{side}_elbow"], lm[f"{side}_wrist"], 0.038),
            (f"{side}_forearm", lm[f"{side}_wrist"], lm[f"{side}_fingertip"], 0.03),
            (f"{side}_thigh", lm[f"{side}_hip"], lm[f"{side}_knee"], 0.075),
            (f"{side}_shin", lm[f"{side}_knee"], lm[f"{side}_ankle"], 0.05),
            (f"{side}_shin", lm[f"{side}_ankle"], lm[f"{side}_toe"], 0.045),
        ]
    return capsules


def segment_distance(points: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Distance (N,) from points (N, 3) to the segment a-b."""
    ab = b - a
    t = np.clip((points - a) @ ab / max(float(ab @ ab), 1e-12), 0.0, 1.0)
    return np.linalg.norm(points - (a + t[:, None] * ab), axis=1)


def skinning_weights(vertices: np.ndarray, triangles: np.ndarray, landmarks: dict[str, np.ndarray],
                     blend_m: float = BLEND_M) -> np.ndarray:
    """Smooth skinning weights (V, len(BONES)) of a rest mesh: nearest-capsule labels averaged over
    mesh neighbours (rows sum to 1). Each averaging spreads a label by about half an edge length squared
    in variance, so 2 (blend_m / mean edge)^2 of them blend over about `blend_m` whatever the resolution.

    Args:
        vertices: (V, 3) rest positions, metres. triangles: (T, 3) int vertex ids.
        landmarks: the MAKEHUMAN_JOINTS landmarks, (3,) each, in the frame of `vertices`.
        blend_m: standard deviation of the blend across a bone boundary, metres.
    """
    from scipy import sparse

    vertices = np.asarray(vertices, np.float64)
    triangles = np.asarray(triangles, np.int64)
    if vertices.ndim != 2 or vertices.shape[1] != 3 or triangles.ndim != 2 or triangles.shape[1] != 3:
        raise ValueError(f"vertices must be (V, 3) and triangles (T, 3), got {vertices.shape}, {triangles.shape}")
    missing = sorted(set(MAKEHUMAN_JOINTS) - set(landmarks))
    if missing:
        raise ValueError(f"skeleton landmarks missing: {missing}")
    capsules = bone_capsules(landmarks)
    margins = np.stack([segment_distance(vertices, a, b) - r for _, a, b, r in capsules])
    bone_of_capsule = np.array([BONES.index(name) for name, *_ in capsules])
    weights = np.zeros((len(vertices), len(BONES)))
    weights[np.arange(len(vertices)), bone_of_capsule[np.argmin(margins, axis=0)]] = 1.0
    n = len(vertices)
    rows = np.concatenate([triangles[:, [0, 1, 2, 1, 2, 0]].reshape(-1), np.arange(n)])
    cols = np.concatenate([triangles[:, [1, 2, 0, 0, 1, 2]].reshape(-1), np.arange(n)])
    adjacency = sparse.csr_matrix((np.ones(len(rows)), (rows, cols)), shape=(n, n))
    adjacency.data[:] = 1.0  # edges shared by two triangles count once
    average = sparse.diags(1.0 / np.asarray(adjacency.sum(axis=1)).ravel()) @ adjacency
    edge = float(np.linalg.norm(vertices[triangles] - vertices[triangles[:, [1, 2, 0]]], axis=2).mean())
    steps = int(min(400, round(2.0 * (blend_m / max(edge, 1e-6)) ** 2)))
    for _ in range(steps):
        weights = average @ weights
    return weights / weights.sum(axis=1, keepdims=True)


def rotation(axis: np.ndarray, angle_deg: float) -> np.ndarray:
    """Right-handed rotation (3, 3) (read-only) by `angle_deg` about the unit-normalised `axis`."""
    return _rotation(tuple(float(c) for c in np.asarray(axis, np.float64).reshape(3)), float(angle_deg))


@functools.lru_cache(maxsize=4096)
def _rotation(axis: tuple[float, float, float], angle_deg: float) -> np.ndarray:
    # cached: reach_extent's pose grids repeat the same few axes and angles hundreds of times
    u = np.array(axis) / np.linalg.norm(axis)
    theta = np.radians(angle_deg)
    k = np.array([[0.0, -u[2], u[1]], [u[2], 0.0, -u[0]], [-u[1], u[0], 0.0]])
    out = np.eye(3) + np.sin(theta) * k + (1.0 - np.cos(theta)) * (k @ k)
    out.flags.writeable = False
    return out


def draw_pose(rng: np.random.Generator, variation: float) -> dict[str, float]:
    """Joint angles (degrees) of one action: `variation` times a uniform draw in POSE_RANGES_DEG."""
    if not 0.0 <= variation <= 1.0:
        raise ValueError(f"pose variation must be in [0, 1], got {variation}")
    draws = rng.uniform(0.0, 1.0, len(POSE_RANGES_DEG))
    return {name: float(variation * (lo + (hi - lo) * u))
            for (name, (lo, hi)), u in zip(POSE_RANGES_DEG.items(), draws)}


def local_rotations(angles_deg: dict[str, float], landmarks: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Rotation (3, 3) of every bone about its joint, relative to its parent, in the rest frame."""
    a = {name: float(angles_deg.get(name, 0.0)) for name in POSE_RANGES_DEG}
    x, y, z = np.eye(3)
    out = {"torso": np.eye(3),
           "head": rotation(y, a["neck_turn"]) @ rotation(x, a["neck_bend"]) @ rotation(z, a["neck_tilt"])}
    for side, sign in (("l", 1.0), ("r", -1.0)):
        # +x is the subject's left: raising the left arm / spreading the left leg turns about +z, the
        # right one about -z; swings turn the hanging limb forward, i.e. about -x
        out[f"{side}_upper_arm"] = (rotation(x, -a[f"{side}_shoulder_swing"])
                                    @ rotation(z, sign * a[f"{side}_shoulder_raise"]))
        upper = landmarks[f"{side}_elbow"] - landmarks[f"{side}_shoulder"]
        out[f"{side}_forearm"] = rotation(np.cross(upper, z), a[f"{side}_elbow_bend"])
        out[f"{side}_thigh"] = rotation(x, -a[f"{side}_hip_swing"]) @ rotation(z, sign * a[f"{side}_hip_spread"])
        out[f"{side}_shin"] = rotation(x, a[f"{side}_knee_bend"])
    return out


def bone_transforms(angles_deg: dict[str, float], skeleton: Skeleton) -> np.ndarray:
    """World transforms (len(BONES), 3, 4) [R | t] of the bones (forward kinematics from the rest pose)."""
    local = local_rotations(angles_deg, skeleton.landmarks)
    world: dict[str, np.ndarray] = {}
    for name in BONES:  # parents come first in BONES
        joint = skeleton.joints[name]
        own = np.column_stack([local[name], joint - local[name] @ joint])
        parent = PARENTS[name]
        if parent is None:
            world[name] = own
        else:
            p = world[parent]
            world[name] = np.column_stack([p[:, :3] @ own[:, :3], p[:, :3] @ own[:, 3] + p[:, 3]])
    return np.stack([world[name] for name in BONES])


def pose_vertices(vertices: np.ndarray, skeleton: Skeleton, angles_deg: dict[str, float]) -> np.ndarray:
    """Linear-blend-skinned positions (V, 3) of rest vertices (V, 3) under joint angles (degrees)."""
    vertices = np.asarray(vertices, np.float64)
    if vertices.shape != (len(skeleton.weights), 3):
        raise ValueError(f"vertices must be ({len(skeleton.weights)}, 3), got {vertices.shape}")
    return skin(vertices, skeleton.weights, bone_transforms(angles_deg, skeleton))


def skin(vertices: np.ndarray, weights: np.ndarray, transforms: np.ndarray) -> np.ndarray:
    """Linear blend skinning: sum over bones of weight x (R p + t); vertices (V, 3), weights (V, B),
    transforms (B, 3, 4); returns (V, 3)."""
    posed = np.zeros_like(vertices, dtype=np.float64)
    for b in range(weights.shape[1]):
        used = weights[:, b] > 0
        if np.any(used):
            posed[used] += weights[used, b, None] * (vertices[used] @ transforms[b, :, :3].T + transforms[b, :, 3])
    return posed


def reach_extent(vertices: np.ndarray, skeleton: Skeleton, variation: float,
                 steps: int = 4, spacing_m: float = 0.02) -> tuple[float, float, float]:
    """Bounding cylinder (radius about +y, y_min, y_max) of the rest mesh and of the poses `draw_pose`
    can give at `variation`, whatever the draws (so framing does not depend on which actions are drawn).

    Each chain's angles sweep a steps^3 grid of their scaled ranges with the other chains at rest: a chain
    moves only the vertices skinned to its bones, so the union over chains bounds every combination (up
    to the grid spacing, ~2 cm for a 0.8 m arm at 4 steps, and to `spacing_m`: the moving vertices are
    thinned to about one per `spacing_m` cube).
    """
    vertices = np.asarray(vertices, np.float64)
    radius = float(np.sqrt(vertices[:, 0] ** 2 + vertices[:, 2] ** 2).max())
    y_min, y_max = float(vertices[:, 1].min()), float(vertices[:, 1].max())
    for chain, names in CHAINS.items():
        columns = [BONES.index(bone) for bone in CHAIN_BONES[chain]]
        moving = np.flatnonzero(skeleton.weights[:, columns].sum(axis=1) > 0)
        _, first = np.unique(np.floor(vertices[moving] / spacing_m).astype(np.int64), axis=0, return_index=True)
        moving = moving[first]
        points, weights = vertices[moving], skeleton.weights[moving]
        grids = [variation * np.linspace(*POSE_RANGES_DEG[name], steps) for name in names]
        for values in np.stack(np.meshgrid(*grids, indexing="ij"), axis=-1).reshape(-1, len(names)):
            posed = skin(points, weights, bone_transforms(dict(zip(names, values)), skeleton))
            radius = max(radius, float(np.sqrt(posed[:, 0] ** 2 + posed[:, 2] ** 2).max()))
            y_min, y_max = min(y_min, float(posed[:, 1].min())), max(y_max, float(posed[:, 1].max()))
    return radius, y_min, y_max
