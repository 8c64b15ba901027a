"""Motion retargeting between rigs: a `SkeletonMotion` of one skeleton -> the same motion on another skeleton.

Steps (all rotations in the common frame of `avatarctl.body.skeleton`: z up, subject facing -y):
1. match joints by vocabulary name (`avatarctl.body.rigs`; SMPL's palm joint `left_hand` stands for the
   `left_middle1` of a rig with fingers); source joints without a target counterpart are dropped (reported),
   target joints without a source stay rigid with their parent (or copy the rotation of the joint that `drives`
   them: anny's other toes follow SMPL's `left_foot`);
2. rest-pose correction per matched joint j: Q_j maps the target's rest bone direction onto the source's
   (j -> its primary child, `rigs.PRIMARY`; branch joints such as the pelvis also align the left-right axis of
   `rigs.LATERAL`). SMPL's T-pose and anny's A-pose differ by ~50 degrees at the shoulders and ~45 at the
   elbows; Q absorbs that. Joints without a primary child (hands, feet, head of a 24-joint SMPL) reuse their
   nearest matched ancestor's Q;
3. world rotations: G'_t[j] = G'_s[src(j)] · Q_j, where G' = V · G · C^T takes each rig's canonical axes (C) and
   world (V) into the common frame; unmatched joints G'_t[j] = G'_t[parent]; locals = G_parent^T · G;
4. translation: the trajectory of the hip centre (midpoint of the hip joints; SMPL's pelvis joint sits ~8 cm above
   it, anny's root at it, so roots are not comparable) is scaled by k = leg length of the target / of the source
   (rest hip -> knee -> ankle, both legs averaged; units cancel), horizontally about the world origin; vertically
   the source floor (its lowest foot joint over the sequence) goes onto the target floor: anny: where its feet
   are when the root stands at the origin (anny's `BodyMotion` convention); other targets: height 0. The target
   root is placed so that its hip centre lands there. A motion of the same rig (an anny skeleton read from BVH)
   keeps its world: rotations copied, root position rescaled.

So each matched bone (joint -> primary child) points, in the world, exactly where the source's does; what differs
is proportions (the target's own bone lengths). `direction_errors` measures that, `floor_errors` the feet.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from avatarctl.body import rigs
from avatarctl.body.skeleton import Skeleton, SkeletonMotion, joint_positions, local_from_world, to_common


@dataclass(frozen=True)
class JointMatch:
    """Which target joint takes which source joint's rotation."""

    pairs: tuple[tuple[int, int], ...]  # (target joint, source joint), target order
    dropped: tuple[str, ...]  # source joints (rig names) of the vocabulary that the target lacks (hands, face)
    helpers: tuple[str, ...]  # source joints outside the vocabulary (twist / helper bones, unnamed BVH joints):
    #                           not mapped, their rotations reach the target through their mapped descendants
    unmatched: tuple[str, ...]  # target joints that no source joint drives (rigid with the parent or driven)
    driven: tuple[tuple[int, int], ...]  # (target joint, target driver joint): copies the driver's local rotation


@dataclass(frozen=True)
class RetargetReport:
    """What a retarget did, for summaries and notes."""

    source: str  # source skeleton name
    target: str
    mapped: tuple[tuple[str, str], ...]  # (source joint, target joint)
    dropped: tuple[str, ...]  # source joints without a target counterpart
    unmatched_target: int  # target joints no source joint drives
    scale: float  # leg-length ratio target / source applied to the root translation
    leg_length: tuple[float, float]  # (source, target) in their own units
    notes: tuple[str, ...]


def match_joints(source: Skeleton, target: Skeleton) -> JointMatch:
    """Joint correspondence by vocabulary name (see the module docstring)."""
    src = source.canonical_index()
    pairs: list[tuple[int, int]] = []
    used: set[int] = set()
    for t, c in enumerate(target.canonical):
        if c is None:
            continue
        s = src.get(c)
        if s is None:  # SMPL palm <-> middle-finger base, when the other rig lacks the same name
            s = next((src[a] for a, b in rigs.ALIASES.items() if b == c and a in src), None)
            if s is None and c in rigs.ALIASES:
                s = src.get(rigs.ALIASES[c])
        if s is not None and s not in used:
            pairs.append((t, s))
            used.add(s)
    driven_to = {t for t, _ in pairs}
    tgt = target.canonical_index()
    driven: list[tuple[int, int]] = []
    for c, bones in target.drives.items():
        if c in tgt and tgt[c] in driven_to:
            driven += [(target.index(b), tgt[c]) for b in bones if target.index(b) not in driven_to]
    vocab = set(rigs.vocabulary())
    dropped = tuple(source.joint_names[s] for s in range(source.num_joints)
                    if s not in used and source.canonical[s] in vocab)
    helpers = tuple(source.joint_names[s] for s in range(source.num_joints)
                    if s not in used and source.canonical[s] not in vocab)
    unmatched = tuple(target.joint_names[t] for t in range(target.num_joints) if t not in driven_to)
    return JointMatch(pairs=tuple(pairs), dropped=dropped, helpers=helpers, unmatched=unmatched,
                      driven=tuple(driven))


def _rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """[..., 3, 3] the smallest rotations taking directions a [..., 3] to b [..., 3]."""
    a = a / np.linalg.norm(a, axis=-1, keepdims=True)
    b = b / np.linalg.norm(b, axis=-1, keepdims=True)
    v = np.cross(a, b)
    c = (a * b).sum(-1)[..., None, None]
    zero = np.zeros(v.shape[:-1])
    K = np.stack([zero, -v[..., 2], v[..., 1], v[..., 2], zero, -v[..., 0], -v[..., 1], v[..., 0], zero],
                 axis=-1).reshape(v.shape[:-1] + (3, 3))
    R = np.eye(3) + K + K @ K / np.maximum(1 + c, 1e-12)
    opposite = c[..., 0, 0] < -1 + 1e-10
    if np.any(opposite):  # half a turn about an axis perpendicular to a
        ao = a[opposite]
        axis = np.cross(ao, np.eye(3)[np.argmin(np.abs(ao), axis=-1)])
        axis /= np.linalg.norm(axis, axis=-1, keepdims=True)
        R[opposite] = 2 * axis[..., :, None] * axis[..., None, :] - np.eye(3)
    return R


def _frame(primary: np.ndarray, lateral: np.ndarray) -> np.ndarray:
    """[3, 3] orthonormal frame (columns): primary, lateral made orthogonal to it, their cross product."""
    e1 = primary / np.linalg.norm(primary)
    e2 = lateral - (lateral @ e1) * e1
    e2 /= np.linalg.norm(e2)
    return np.stack([e1, e2, np.cross(e1, e2)], axis=1)


def _descendant(skel: Skeleton, joint: int, of: int) -> bool:
    while joint > of:
        joint = skel.parents[joint]
    return joint == of


@dataclass(frozen=True)
class RestCorrection:
    """Per matched target joint: the rest-pose correction Q_j and the bone it aims (common frame)."""

    Q: dict[int, np.ndarray]  # target joint -> [3, 3], Q_j · target rest bone = source rest bone direction
    aim: dict[int, tuple[int, int]]  # target joint -> (target child, source child) of its primary bone
    bent: frozenset[int]  # target joints whose source bone passes unmatched source joints (helper bones)


def rest_corrections(source: Skeleton, target: Skeleton, match: JointMatch) -> RestCorrection:
    """Q_j and the aimed bone of every matched target joint (see the module docstring, step 2)."""
    Rs = source.rest @ to_common(source.canonical_up).T  # [joints, 3]
    Rt = target.rest @ to_common(target.canonical_up).T
    t_of = {target.canonical[t]: t for t, _ in match.pairs}
    s_of = {target.canonical[t]: s for t, s in match.pairs}
    Q: dict[int, np.ndarray] = {}
    aim: dict[int, tuple[int, int]] = {}
    bent: set[int] = set()
    matched_s = {s for _, s in match.pairs}
    for t, s in match.pairs:
        name = target.canonical[t]
        cands = rigs.PRIMARY.get(name, ())
        if not cands:  # any single matched child (BVH / anny bones outside the vocabulary tables)
            kids = [c for c in t_of if c != name and _descendant(target, t_of[c], t)
                    and target.parents[t_of[c]] == t]
            cands = tuple(kids) if len(kids) == 1 else ()
        child = next((c for c in cands if c in t_of and _descendant(target, t_of[c], t)
                      and _descendant(source, s_of[c], s)), None)
        vt = None if child is None else Rt[t_of[child]] - Rt[t]
        vs = None if child is None else Rs[s_of[child]] - Rs[s]
        if vt is None or np.linalg.norm(vt) < 1e-9 or np.linalg.norm(vs) < 1e-9:
            p = target.parents[t]
            while p >= 0 and p not in Q:
                p = target.parents[p]
            Q[t] = Q[p] if p >= 0 else np.eye(3)
            continue
        aim[t] = (t_of[child], s_of[child])
        k = source.parents[s_of[child]]
        while k != s:
            if k not in matched_s:
                bent.add(t)
            k = source.parents[k]
        lat = rigs.LATERAL.get(name)
        if lat is not None and all(c in t_of for c in lat):
            lt = Rt[t_of[lat[0]]] - Rt[t_of[lat[1]]]
            ls = Rs[s_of[lat[0]]] - Rs[s_of[lat[1]]]
            if np.linalg.norm(np.cross(lt, vt)) > 1e-6 and np.linalg.norm(np.cross(ls, vs)) > 1e-6:
                Q[t] = _frame(vs, ls) @ _frame(vt, lt).T
                continue
        Q[t] = _rotation_between(vt, vs)
    return RestCorrection(Q=Q, aim=aim, bent=frozenset(bent))


def leg_length(skel: Skeleton) -> float:
    """Mean rest length of hip -> knee -> ankle over both legs (skeleton units)."""
    lengths = [v for v in (skel.bone_length(chain) for chain in rigs.LEGS) if v is not None]
    if not lengths:
        raise ValueError(f"the {skel.name} skeleton has no mapped legs (hips, knees, ankles)")
    return float(np.mean(lengths))


def _feet(skel: Skeleton) -> list[int]:
    idx = skel.canonical_index()
    feet = [idx[c] for c in rigs.FEET if c in idx]
    if not feet:
        raise ValueError(f"the {skel.name} skeleton has no mapped ankles or feet")
    return feet


def _hips(skel: Skeleton) -> list[int]:
    idx = skel.canonical_index()
    if not all(c in idx for c in rigs.HIPS):
        raise ValueError(f"the {skel.name} skeleton has no mapped hips")
    return [idx[c] for c in rigs.HIPS]


def floor_level(target: Skeleton) -> float:
    """Height (common frame, target units) of the target's lowest foot joint when standing: anny's with its root at
    the origin in the reference pose, 0 for every other rig."""
    if target.name != "anny":
        return 0.0
    Rt = target.rest @ to_common(target.canonical_up).T
    return float(Rt[_feet(target), 2].min() - Rt[0, 2])


def common_positions(motion: SkeletonMotion) -> np.ndarray:
    """[frames, joints, 3] posed joint heads in the common frame (z up)."""
    return motion.joint_positions() @ to_common(motion.world_up).T


def retarget(motion: SkeletonMotion, target: Skeleton, world_up: str = "z") -> tuple[SkeletonMotion,
                                                                                          RetargetReport]:
    """`motion` on `target` (see the module docstring); the result lives in a world with up axis `world_up`."""
    source = motion.skeleton
    match = match_joints(source, target)
    if not match.pairs or match.pairs[0][0] != 0:
        raise ValueError(f"no {source.name} joint matches the {target.name} root ({target.canonical[0]}); "
                         f"{len(match.pairs)} joints matched")
    rc = rest_corrections(source, target, match)
    Cs, Ct = to_common(source.canonical_up), to_common(target.canonical_up)
    Vs, Vt = to_common(motion.world_up), to_common(world_up)
    Gs = Vs @ motion.world_rotations() @ Cs.T  # [frames, joints, 3, 3] common canonical -> common world
    Rs = source.rest @ Cs.T
    Ps = joint_positions(Gs, Rs, source.parents, motion.root_position @ Vs.T)  # [frames, J, 3] common world
    F, Jt = motion.num_frames, target.num_joints
    Gt = np.empty((F, Jt, 3, 3))
    src_of = dict(match.pairs)
    for j in range(Jt):
        if j in src_of:
            s = src_of[j]
            Gt[:, j] = Gs[:, s] @ rc.Q[j]
            if j in rc.bent:  # source helper bones between s and its aimed child bend the bone: follow them
                sc = rc.aim[j][1]
                Gt[:, j] = _rotation_between(Gs[:, s] @ (Rs[sc] - Rs[s]), Ps[:, sc] - Ps[:, s]) @ Gt[:, j]
        else:
            Gt[:, j] = Gt[:, target.parents[j]] if j else np.eye(3)
    local = local_from_world(Vt.T @ Gt @ Ct, target.parents)  # back into the target's canonical axes and world
    for t, driver in match.driven:
        local[:, t] = local[:, driver]
    # translation: the hip centre's trajectory, scaled by leg length, the source floor onto the target floor
    Ls, Lt = leg_length(source), leg_length(target)
    k = Lt / Ls
    Rt = target.rest @ Ct.T
    same = source.canonical == target.canonical and source.parents == target.parents and \
        all(np.abs(q - np.eye(3)).max() < 1e-5 for q in rc.Q.values())
    if same:  # one rig in another file (anny -> BVH -> anny) keeps its world
        root_t = k * Ps[:, src_of[0]]
    else:
        floor_s = float(Ps[:, _feet(source), 2].min())
        hips_s = Ps[:, _hips(source)].mean(1)  # [frames, 3]
        at_origin = joint_positions(Gt, Rt, target.parents, np.zeros((F, 3)))
        hips_t = k * hips_s
        hips_t[:, 2] = k * (hips_s[:, 2] - floor_s) + floor_level(target)
        root_t = hips_t - at_origin[:, _hips(target)].mean(1)
    out = SkeletonMotion(skeleton=target, local=local, root_position=root_t @ Vt, fps=motion.fps, world_up=world_up,
                         frame_index=motion.frame_index)
    notes = ["same rig: rotations copied, translation rescaled"] if same else []
    if match.dropped:
        notes.append(f"dropped {len(match.dropped)} {source.name} joints the {target.name} rig lacks: "
                     + _summarise(match.dropped))
    if match.helpers:
        notes.append(f"{len(match.helpers)} {source.name} joints outside the joint vocabulary (helper bones, unknown "
                     "names) are not mapped: their rotations reach the target through the mapped joints below them")
    n_free = len(match.unmatched) - len(match.driven)
    if n_free:
        notes.append(f"{n_free} {target.name} joints have no source joint and stay rigid with their parent")
    report = RetargetReport(source=source.name, target=target.name,
                            mapped=tuple((source.joint_names[s], target.joint_names[t]) for t, s in match.pairs),
                            dropped=match.dropped, unmatched_target=len(match.unmatched), scale=k,
                            leg_length=(Ls, Lt), notes=tuple(notes))
    return out, report


def _summarise(names: tuple[str, ...], most: int = 6) -> str:
    fingers = [n for n in names if rigs.group_of(n) == "hands"]
    rest = [n for n in names if n not in fingers]
    parts = rest[:most] + ([f"… +{len(rest) - most}"] if len(rest) > most else [])
    if fingers:
        parts.append(f"{len(fingers)} hand/finger joints")
    return ", ".join(parts)


# ---- measuring a retarget -------------------------------------------------------------------------------------
@dataclass(frozen=True)
class DirectionErrors:
    """Per matched bone (joint -> primary child): angle between the source's and the target's world direction."""

    bones: tuple[str, ...]  # [bones] "joint->child" (vocabulary names)
    groups: tuple[str, ...]  # [bones] legs | spine | arms | hands | head
    degrees: np.ndarray  # [frames, bones]
    rest_degrees: np.ndarray  # [bones] the same angle between the two rest poses (proportions, before posing)


def direction_errors(source: SkeletonMotion, target: SkeletonMotion) -> DirectionErrors:
    """Bone direction agreement of a retarget, in the common frame. A bone is a matched joint and its primary
    child, when both rigs have both."""
    match = match_joints(source.skeleton, target.skeleton)
    rc = rest_corrections(source.skeleton, target.skeleton, match)
    src_of = dict(match.pairs)
    Ps, Pt = common_positions(source), common_positions(target)
    Rs = source.skeleton.rest @ to_common(source.skeleton.canonical_up).T
    Rt = target.skeleton.rest @ to_common(target.skeleton.canonical_up).T
    bones, groups, errs, rest = [], [], [], []

    def angle(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        cos = (a * b).sum(-1) / (np.linalg.norm(a, axis=-1) * np.linalg.norm(b, axis=-1))
        return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))

    for tj, (tc, sc) in rc.aim.items():
        sj = src_of[tj]
        bones.append(f"{target.skeleton.canonical[tj]}->{target.skeleton.canonical[tc]}")
        groups.append(rigs.group_of(target.skeleton.canonical[tj] or ""))
        errs.append(angle(Pt[:, tc] - Pt[:, tj], Ps[:, sc] - Ps[:, sj]))
        rest.append(float(angle(Rt[tc] - Rt[tj], Rs[sc] - Rs[sj])))
    return DirectionErrors(bones=tuple(bones), groups=tuple(groups), degrees=np.stack(errs, axis=1),
                           rest_degrees=np.array(rest))


@dataclass(frozen=True)
class FloorErrors:
    """How well the feet keep their height over the floor: target vs k · source, per frame (target units)."""

    source_height: np.ndarray  # [frames] lowest foot joint above the source floor, scaled by k
    target_height: np.ndarray  # [frames] lowest foot joint above the target floor
    root_error: np.ndarray  # [frames] |target hip centre - k · source hip centre| horizontally

    @property
    def height_error(self) -> np.ndarray:
        return np.abs(self.target_height - self.source_height)


def floor_errors(source: SkeletonMotion, target: SkeletonMotion, report: RetargetReport) -> FloorErrors:
    """Feet heights and horizontal root track of a retarget (common frame)."""
    Ps, Pt = common_positions(source), common_positions(target)
    fs, ft = _feet(source.skeleton), _feet(target.skeleton)
    hs = Ps[:, fs, 2].min(1)
    ht = Pt[:, ft, 2].min(1)
    k = report.scale
    hips_s, hips_t = Ps[:, _hips(source.skeleton)].mean(1), Pt[:, _hips(target.skeleton)].mean(1)
    root_err = np.linalg.norm(hips_t[:, :2] - k * hips_s[:, :2], axis=1)
    return FloorErrors(source_height=k * (hs - hs.min()), target_height=ht - floor_level(target.skeleton),
                       root_error=root_err)
