"""Procedural anny motion: a training choreography (walk, 90 deg turn, twirl) and a novel-pose test choreography
(high-knee march with raised arms and torso twist, then a twirl the other way), with a warm-up before frame 0.
`SynthConfig.motion = "turn"` replaces them with a 360 deg turn in place in an A-pose (PeopleSnapshot-like) and
held-out poses that turn on with lowered arms and bent elbows and knees.

Pose parameters are anny's "local-ref" deltas [frames, 104, 4, 4] (FACTS.md section 4): a delta is a rotation in
the world-aligned axes of the reference (A-)pose about the bone head, composed down the chain; the root delta is
the root's world pose (rotation about +z = heading, translation = position). anny world: +x subject's left,
+y subject's back (the subject faces -y at heading 0), +z up, metres. Sign conventions used here:
hip flexion -a about +x (`upperleg01.*`), knee flexion +a about +x (`lowerleg01.*`), arm lowered from the A-pose
+a about +y (left) / -a (right) on `upperarm01.*`, arm forward swing -a about +x, elbow flexion +a about the
bone's own x axis (`reference_bone_orientations[lowerarm01.*][:, 0]`), torso twist +a about +z (`spine03`),
forward lean +a about +x (`spine05`; FACTS.md says -a, but measured here -a moves the head towards +y,
i.e. backwards). Arms are never lowered by more than 25 deg (hands would snag the skirt).

Timeline (rows of `ProceduralMotion`, at `sim_fps`): `warmup_frames` rows (the body blends from the reference
pose to the first pose while the cloth settles), the training rows, `transition_frames` rows blending into the
test choreography, the test rows; every `stride`-th training/test row is written. Only warm-up and transition
rows are unwritten; the cloth is simulated through all of them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from avatarctl.synth.config import SynthConfig

# bone indices of anny's default rig (checked against `anny.Anny().bone_labels` at run time)
BONES = {"root": 0, "upperleg01.L": 2, "lowerleg01.L": 4, "upperleg01.R": 22, "lowerleg01.R": 24,
         "spine05": 41, "spine03": 43, "upperarm01.L": 48, "lowerarm01.L": 50, "upperarm01.R": 74,
         "lowerarm01.R": 76}
MAX_ARM_LOWER = math.radians(25.0)
MAX_TWIRL_REV_S = 1.3  # peak angular speed of a twirl, revolutions per second
PHENOTYPE_LABELS = ("gender", "age", "muscle", "weight", "height", "proportions")


@dataclass(frozen=True)
class Limbs:
    """Joint angles of one frame (radians) and the root pose; arrays broadcast over frames."""

    heading: np.ndarray  # [frames] rotation about +z; 0 = facing -y
    position: np.ndarray  # [frames, 3] root position, metres
    hip: np.ndarray  # [frames, 2] flexion (L, R), + = thigh forward
    knee: np.ndarray  # [frames, 2] flexion (L, R), + = shin back
    arm_swing: np.ndarray  # [frames, 2] + = arm forward
    arm_lower: np.ndarray  # [frames, 2] + = arm towards the body from the A-pose, <= 25 deg
    elbow: np.ndarray  # [frames, 2] extra flexion over the A-pose's pre-flexed forearm
    twist: np.ndarray  # [frames] torso twist about +z
    lean: np.ndarray  # [frames] forward lean

    def scaled(self, w: np.ndarray) -> "Limbs":
        """Every angle and the root pose scaled by `w` [frames] (w=0: reference pose at the origin)."""
        c = w[:, None]
        return Limbs(self.heading * w, self.position * c, self.hip * c, self.knee * c, self.arm_swing * c,
                     self.arm_lower * c, self.elbow * c, self.twist * w, self.lean * w)


@dataclass(frozen=True)
class ProceduralMotion:
    """The simulated timeline: warm-up rows then the capture rows."""

    pose_parameters: np.ndarray  # [rows, 104, 4, 4] float32 anny local-ref deltas
    written_rows: np.ndarray  # [frames] row of each written frame
    train_frames: int  # the first `train_frames` written frames are training frames
    phenotype: np.ndarray  # [6] in PHENOTYPE_LABELS order
    fps: float

    @property
    def rows(self) -> int:
        return int(self.pose_parameters.shape[0])


def _smooth(x: np.ndarray) -> np.ndarray:
    """Smootherstep on [0, 1] (zero first and second derivative at both ends)."""
    x = np.clip(x, 0.0, 1.0)
    return x * x * x * (x * (6 * x - 15) + 10)


def _window(u: np.ndarray, a: float, b: float) -> np.ndarray:
    return _smooth((u - a) / (b - a))


def twirl_angle(window_s: float, turns: float = 1.0) -> float:
    """Twirl angle (radians) over a smootherstep window of `window_s` seconds: `turns` full turns unless that
    would exceed MAX_TWIRL_REV_S at the peak (smootherstep peaks at 1.875 x the mean speed)."""
    return 2 * np.pi * min(turns, MAX_TWIRL_REV_S * window_s / 1.875)


def _rot(axis: np.ndarray, angle: np.ndarray) -> np.ndarray:
    """Rodrigues: unit axis [3], angles [frames] -> [frames, 3, 3]."""
    axis = np.asarray(axis, dtype=np.float64)
    axis = axis / np.linalg.norm(axis)
    Kx = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    a = np.asarray(angle, dtype=np.float64)[:, None, None]
    return np.eye(3) + np.sin(a) * Kx + (1 - np.cos(a)) * (Kx @ Kx)


_X, _Y, _Z = np.eye(3)


def limbs_to_pose_parameters(limbs: Limbs, elbow_axes: np.ndarray) -> np.ndarray:
    """Limbs -> anny local-ref deltas [frames, 104, 4, 4] (float32). `elbow_axes` [2, 3]: bone x axes (L, R)."""
    n = limbs.heading.shape[0]
    P = np.broadcast_to(np.eye(4), (n, 104, 4, 4)).copy()
    P[:, BONES["root"], :3, :3] = _rot(_Z, limbs.heading)
    P[:, BONES["root"], :3, 3] = limbs.position
    for s, side in enumerate(("L", "R")):
        sign = 1.0 if side == "L" else -1.0
        P[:, BONES[f"upperleg01.{side}"], :3, :3] = _rot(_X, -limbs.hip[:, s])
        P[:, BONES[f"lowerleg01.{side}"], :3, :3] = _rot(_X, limbs.knee[:, s])
        lower = np.clip(limbs.arm_lower[:, s], -MAX_ARM_LOWER, MAX_ARM_LOWER)
        P[:, BONES[f"upperarm01.{side}"], :3, :3] = _rot(_X, -limbs.arm_swing[:, s]) @ _rot(_Y, sign * lower)
        P[:, BONES[f"lowerarm01.{side}"], :3, :3] = _rot(elbow_axes[s], limbs.elbow[:, s])
    P[:, BONES["spine03"], :3, :3] = _rot(_Z, limbs.twist)
    P[:, BONES["spine05"], :3, :3] = _rot(_X, limbs.lean)
    return P.astype(np.float32)


def _gait(phase: np.ndarray, amp: np.ndarray, hip_amp: float, knee_amp: float, arm_amp: float
          ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A stepping cycle: hip [f,2], knee [f,2], arm swing [f,2], vertical bob [f]; `phase` in cycles."""
    s = np.sin(2 * np.pi * phase)
    hip = np.stack([s, -s], -1) * hip_amp
    kl = (0.5 + 0.5 * np.sin(2 * np.pi * phase + 0.9)) ** 2
    kr = (0.5 + 0.5 * np.sin(2 * np.pi * phase + 0.9 + np.pi)) ** 2
    knee = np.stack([kl, kr], -1) * knee_amp
    arm = np.stack([-s, s], -1) * arm_amp
    bob = -0.012 * (0.5 - 0.5 * np.cos(4 * np.pi * phase))
    a = amp[:, None]
    return hip * a, knee * a, arm * a, bob * amp


def _train_limbs(t: np.ndarray, dur: float, rng: np.random.Generator) -> Limbs:
    """Walk towards -y, turn 90 deg left while stepping, hold, twirl +360 deg, hold (same pose as the first hold).

    The twirl is a full turn when the segment is long enough (>= ~4 s); shorter segments twirl less.
    """
    u = t / dur
    n = t.shape[0]
    step_hz = rng.uniform(0.8, 1.0)
    hip_amp, knee_amp, arm_amp = math.radians(rng.uniform(18, 24)), math.radians(rng.uniform(35, 45)), \
        math.radians(rng.uniform(12, 18))
    amp = 1.0 - _window(u, 0.32, 0.42)  # gait fades out at the end of the turn
    hip, knee, arm, bob = _gait(step_hz * t, amp, hip_amp, knee_amp, arm_amp)
    walk = _window(u, 0.0, 0.3)
    y = 0.22 - 0.44 * walk
    heading = math.radians(90) * _window(u, 0.27, 0.42) + twirl_angle(0.38 * dur) * _window(u, 0.5, 0.88)
    pose = _window(u, 0.38, 0.45)  # blend the arms into the twirl pose
    lower_twirl, swing_twirl = math.radians(rng.uniform(5, 10)), math.radians(rng.uniform(6, 12))
    arm_lower = np.full((n, 2), math.radians(4.0)) * (1 - pose[:, None]) + lower_twirl * pose[:, None]
    elbow = np.full((n, 2), math.radians(8.0)) + math.radians(10.0) * pose[:, None]
    return Limbs(heading=heading, position=np.stack([np.zeros(n), y, bob], -1), hip=hip, knee=knee,
                 arm_swing=arm + swing_twirl * pose[:, None], arm_lower=arm_lower, elbow=elbow,
                 twist=np.zeros(n), lean=np.zeros(n))


def _test_limbs(t: np.ndarray, dur: float, lead: float, rng: np.random.Generator, start: Limbs) -> Limbs:
    """High-knee march with arms raised forward, torso twist and heading sway; then a twirl the other way
    (a full turn when the segment is long enough, >= ~6 s). `t` starts at -`lead` seconds: the unwritten
    transition from the training segment's last pose, so that every written test frame is a novel pose."""
    u = t / dur
    n = t.shape[0]
    step_hz = rng.uniform(1.15, 1.35)
    amp = _window(t, -lead, -lead / 3) * (1.0 - _window(u, 0.55, 0.65))
    hip, knee, arm, bob = _gait(step_hz * t, amp, math.radians(rng.uniform(30, 36)),
                                math.radians(rng.uniform(55, 65)), math.radians(6.0))
    hip = hip + math.radians(6.0) * amp[:, None]  # thighs kept forward: marching, not walking
    march = _window(t, -lead, 0.6 * dur)
    x = 0.22 * march
    y = start.position[-1, 1] + (0.05 - start.position[-1, 1]) * march
    sway = math.radians(25.0) * np.sin(2 * np.pi * 0.5 * step_hz * t) * amp
    heading = start.heading[-1] + sway - twirl_angle(0.3 * dur) * _window(u, 0.62, 0.92)
    arms_up = _window(t, -lead, -0.1 * lead)[:, None]
    lower = math.radians(rng.uniform(18, 24))
    arm_lower = start.arm_lower[-1] * (1 - arms_up) + np.array([lower, lower * 0.6]) * arms_up
    arm_swing = start.arm_swing[-1] * (1 - arms_up) + arms_up * np.array(
        [math.radians(22.0), math.radians(-8.0)]) + arm
    elbow = start.elbow[-1] * (1 - arms_up) + arms_up * np.array([math.radians(35.0), math.radians(15.0)])
    twist = math.radians(15.0) * np.sin(2 * np.pi * step_hz * t) * amp
    lean = math.radians(5.0) * _window(u, 0.6, 0.7)
    return Limbs(heading=heading, position=np.stack([x, y, bob], -1), hip=hip, knee=knee, arm_swing=arm_swing,
                 arm_lower=arm_lower, elbow=elbow, twist=twist, lean=lean)


def _turn_limbs(t: np.ndarray, dur: float, rng: np.random.Generator) -> Limbs:
    """Turning in place through 360 deg (left) at a near-constant speed, arms in an A-pose with a little sway, legs
    straight: PeopleSnapshot's capture motion."""
    u = t / dur
    n = t.shape[0]
    heading = 2 * np.pi * np.clip(u, 0.0, 1.0)  # [frames] one full turn at constant speed
    sway = math.radians(rng.uniform(2.0, 4.0)) * np.sin(2 * np.pi * 0.5 * t)
    arm_lower = np.stack([np.full(n, math.radians(3.0)) + sway, np.full(n, math.radians(3.0)) - sway], -1)
    zeros2 = np.zeros((n, 2))
    return Limbs(heading=heading, position=np.zeros((n, 3)), hip=zeros2, knee=zeros2, arm_swing=zeros2,
                 arm_lower=arm_lower, elbow=np.full((n, 2), math.radians(8.0)), twist=np.zeros(n), lean=np.zeros(n))


def _turn_test_limbs(t: np.ndarray, dur: float, lead: float, rng: np.random.Generator, start: Limbs) -> Limbs:
    """Held-out poses after the turn: turning on by half a turn while the arms lower towards the body, the elbows
    and knees bend and the torso twists; `t` starts at -`lead` s (the unwritten transition)."""
    n = t.shape[0]
    blend = _window(t, -lead, 0.3 * dur)[:, None]
    heading = start.heading[-1] + np.pi * _window(t, -lead, dur)
    arm_lower = start.arm_lower[-1] * (1 - blend) + math.radians(rng.uniform(18, 24)) * blend
    elbow = start.elbow[-1] * (1 - blend) + np.array([math.radians(40.0), math.radians(25.0)]) * blend
    knee = np.array([math.radians(15.0), math.radians(5.0)]) * blend
    hip = np.array([math.radians(8.0), math.radians(2.0)]) * blend
    swing = np.array([math.radians(15.0), math.radians(-10.0)]) * blend
    twist = math.radians(12.0) * np.sin(2 * np.pi * 0.4 * t) * blend[:, 0]
    return Limbs(heading=heading, position=np.zeros((n, 3)), hip=hip, knee=knee, arm_swing=swing,
                 arm_lower=arm_lower, elbow=elbow, twist=twist, lean=np.zeros(n))


def _concat(a: Limbs, b: Limbs) -> Limbs:
    return Limbs(*(np.concatenate([getattr(a, f), getattr(b, f)]) for f in Limbs.__dataclass_fields__))


def make_phenotype(seed: int) -> np.ndarray:
    """[6] anny phenotype (PHENOTYPE_LABELS order) drawn from the seed, kept near the average adult."""
    rng = np.random.default_rng([seed, 2])
    lo = np.array([0.0, 0.42, 0.3, 0.3, 0.35, 0.4])
    hi = np.array([1.0, 0.58, 0.7, 0.6, 0.65, 0.6])
    return (lo + (hi - lo) * rng.random(6)).astype(np.float32)


def make_motion(config: SynthConfig, elbow_axes: np.ndarray) -> ProceduralMotion:
    """The whole timeline for `config` (deterministic in `config.seed`). `elbow_axes` [2, 3] from anny."""
    rng = np.random.default_rng([config.seed, 1])
    fps, stride = config.sim_fps, config.stride
    n_train, n_test = config.train_frames * stride, config.test_frames * stride
    t_train = np.arange(n_train) / fps
    train_fn, test_fn = (_turn_limbs, _turn_test_limbs) if config.motion == "turn" else (_train_limbs, _test_limbs)
    train = train_fn(t_train, n_train / fps, rng)
    # unwritten transition rows between the segments (the cloth keeps simulating through them)
    n_lead = config.transition_frames
    t_test = np.arange(-n_lead, n_test) / fps
    test = test_fn(t_test, n_test / fps, n_lead / fps, rng, train)
    capture = _concat(train, test)
    # warm-up: a third settles in the reference pose, then the first pose is blended in
    W = config.warmup_frames
    settle = W // 3
    w = _smooth((np.arange(W) - settle + 1) / max(W - settle, 1))
    first = Limbs(*(np.repeat(getattr(capture, f)[:1], W, axis=0) for f in Limbs.__dataclass_fields__))
    limbs = _concat(first.scaled(w), capture)
    P = limbs_to_pose_parameters(limbs, elbow_axes)
    k = np.arange(config.frames)
    rows = W + k * stride + np.where(k >= config.train_frames, n_lead, 0)
    return ProceduralMotion(pose_parameters=P, written_rows=rows.astype(np.int64), train_frames=config.train_frames,
                            phenotype=make_phenotype(config.seed), fps=fps / stride)
