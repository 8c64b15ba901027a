"""Data-parallel fitting over the ranks of a `torch.distributed` group (`avatarctl.dist`): `Replicas`.

Every rank holds a full copy of the model. The step's batch (`FitConfig.rays_per_batch` rays over
`images_per_batch` images) is cut into S *ray shards*: shard k owns the (training frame, training view) pairs
pairs[k::S] (pairs in frame-major order), draws `images_per_batch / S` images from them and
`rays_per_batch / S` rays, with its own sampler generator and its own noise generator (cVAE posterior sample,
sample jitter, occupancy exploration), seeded `seed + 1_000_003 k` (+1 for the noise): with S = 1 that is the
single-process fit exactly. Rank r works on shards r, r + N, ... (N ranks; N must divide S). So a fit samples the
same rays and noise with any N dividing S: the 2-rank run of S = 2 equals a 1-rank run of S = 2 up to float
rounding (tests/test_fit_distributed.py), and a fit started on 2 ranks resumes on 1 (or 2 on 4 with S = 4, ...).
Each rank's frame cache only holds its shard's images.

The rule (effective batch and learning rate): `rays_per_batch` and `images_per_batch` are the *global* batch. N
does not change the optimisation: each rank computes the loss of its R / N rays (Eq. 12 is normalised per ray, the
regularisers per frame, so each rank's loss is the mean over its share), the gradients are averaged over the ranks
(= the gradient of the loss of all R rays), and lr, schedule and step count stay as configured. What N changes is
the time per step. To fill more devices, grow the global batch with `--set rays_per_batch=.. images_per_batch=..`
(a new recipe: Adam's update is invariant to the gradient scale, so lr stays; the sqrt(k) rule for a k-times batch
is not applied automatically).

Synchronisation per step (after the backward pass), all in one flat SUM all-reduce plus one MAX all-reduce:
- gradients: explicit all-reduce of all parameter gradients as one flat buffer, divided by N; a parameter that no
  rank gave a gradient stays without one (Adam skips it, as in one process). Why not `DistributedDataParallel`:
  a step is three calls (`node_state`, `render`, `losses`), not one `forward`, and the sparse per-node evaluation
  leaves parameters without gradients on a rank whose rays miss them (DDP would need `find_unused_parameters` and
  its graph walk every step); DDP would also broadcast rank 0's buffers over the occupancy grids each rank updated
  from its own rays. The price: the all-reduce does not overlap the backward pass.
- stop flags (Ctrl-C, time budget, snapshot due) and the loss terms ride in the same buffer, so every rank stops
  after the same step and logs the mean losses;
- per-frame parameters (the pose-refinement corrections delta / tau of model/pose_refine.py, the per-frame latent
  codes) are parameters like any other: a frame's correction gets gradients only on the rank whose rays saw it,
  and the average makes every rank apply the same update. The pose penalty is a mean over a rank's frames, so it is
  averaged like the other regularisers;
- the occupancy grids (`model.occupancy`, updated in the forward pass from each rank's own densities): see
  `merge_occupancy`; all ranks end the step with the grid one process would have.

Each shard's renders go through their training cameras' colour transforms before the loss when
`model.colour.enabled` (fit/steps.py `camera_colour_rays`, `camera_colour_crops`; model/colour.py): their parameters are the
model's, averaged like the others.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Callable

import torch

from avatarctl.dist import DistEnv, active
from avatarctl.errors import InputError

if TYPE_CHECKING:
    from avatarctl.fit.data import PairSampler
    from avatarctl.fit.steps import TrainingSteps
    from avatarctl.model.avatar import ImageOutputs, NodeState, RenderOutputs, SlrfAvatar
    from avatarctl.model.losses import LossTerms

SHARD_SEED_STRIDE = 1_000_003
_UNCHANGED = -2.0  # below every occupancy value (UNSEEN = -1, densities >= 0)


def shard_seed(seed: int, shard: int) -> int:
    """Seed of shard `shard`'s ray sampler (its noise generator: + 1); shard 0 keeps the single-process seed."""
    return int(seed) + SHARD_SEED_STRIDE * int(shard)


def check_shards(shards: int, world: int, rays: int, images: int, pairs: int) -> None:
    """The batch must split evenly over the shards and the shards over the ranks (see the module docstring)."""
    fix = (f"use --nproc dividing the shards, or --set rays_per_batch / images_per_batch to multiples of {shards} "
           "(they are the global batch)")
    if shards < 1:
        raise InputError(f"ray shards must be >= 1, got {shards}", where="--shards", fix="e.g. --shards 2")
    if shards % world:
        raise InputError(f"{world} ranks cannot share {shards} ray shards evenly", where="--nproc / --shards", fix=fix)
    if rays % shards or images % shards:
        raise InputError(f"rays_per_batch {rays} and images_per_batch {images} must be multiples of the {shards} "
                         "ray shards", where="--nproc / --shards", fix=fix)
    if shards > pairs:
        raise InputError(f"{shards} ray shards but only {pairs} (training frame, training view) pairs",
                         where="--nproc / --shards", fix="use fewer ranks / shards")


def merge_occupancy(before: torch.Tensor, afters: list[torch.Tensor]) -> torch.Tensor:
    """The occupancy grid one process would have after observing the union of what each copy observed.

    before [cells]: the grid at the start of the step (the same everywhere); afters: [cells] each, the grid after a
    copy applied its own observations (`model.occupancy.update_occupancy`: a cell observed becomes
    a = max(base, d) with base = decay * before (0 if unseen) and d its largest observed density). One process
    observing everything gives max(base, max_k d_k) = max over the copies that observed the cell of a_k; a copy that
    did not observe it leaves it at `before`. So: a cell some copy changed takes the largest changed value, else
    `before`. (A copy whose observation left a cell unchanged, a_k == before, is taken as not observing it; that
    differs from one process only when another copy changed the cell to a value below `before`, i.e. a density
    exactly equal to the cached one.)
    """
    best = torch.full_like(before, _UNCHANGED)
    for a in afters:
        best = torch.maximum(best, changed_values(before, a))
    return torch.where(best > _UNCHANGED, best, before)


def changed_values(before: torch.Tensor, after: torch.Tensor) -> torch.Tensor:
    """after where it differs from before, else a value below any occupancy ([cells])."""
    return torch.where(after != before, after, torch.full_like(after, _UNCHANGED))


@dataclass(frozen=True)
class StepSync:
    """What the ranks agreed on after a step."""

    stop: bool  # some rank was asked to stop (Ctrl-C / StopFlag)
    budget: bool  # rank 0's time budget is spent
    snapshot: bool  # rank 0's next snapshot time is reached
    losses: dict[str, float] | None  # loss terms averaged over the ranks (None in one process: read them locally)


class Replicas:
    """This rank's share of a data-parallel fit: its ray shards (each a sampler and two generators), the step's
    forward pass over them, and the synchronisation after the backward pass (see the module docstring)."""

    def __init__(self, env: DistEnv | None, shards: int, steps: "TrainingSteps",
                 make_sampler: Callable[[list | None, int, int], "PairSampler"], train_frames: list[int],
                 train_views: list[str], rays: int, images: int, seed: int, device: torch.device):
        """`make_sampler(pairs, rays, images)`: a sampler of `steps` over `pairs` (None: all) drawing that many rays
        (ray-marched fields) and images per step."""
        world = env.world_size if env is not None else 1
        pairs = [(f, v) for f in train_frames for v in train_views]
        check_shards(shards, world, rays, images, len(pairs))
        self.env, self.shards, self.world, self.device, self.steps = env, shards, world, device, steps
        self.local = [k for k in range(shards) if k % world == (env.rank if env is not None else 0)]
        self.samplers = {k: make_sampler(None if shards == 1 else pairs[k::shards], rays // shards, images // shards)
                         for k in self.local}
        self.reseed(seed)

    @property
    def distributed(self) -> bool:
        return active(self.env)

    def reseed(self, seed: int) -> None:
        """Fresh generators for every local shard from `seed` (shard_seed)."""
        self.sampler_gens = {k: torch.Generator().manual_seed(shard_seed(seed, k)) for k in self.local}
        self.noise_gens = {k: torch.Generator(device=self.device).manual_seed(shard_seed(seed, k) + 1)
                           for k in self.local}

    # ---- one step -----------------------------------------------------------------------------------------------
    def forward(self, model: "SlrfAvatar", background: torch.Tensor, jitter: bool
                ) -> tuple["LossTerms", "RenderOutputs | ImageOutputs", int]:
        """Sample the local shards, compute node states, render and the loss of Eq. 11 over this rank's rays (or
        crops): `TrainingSteps.forward` (fit/steps.py). -> (loss terms, render outputs: `RenderOutputs` of rays,
        `ImageOutputs` of the rasterized field's crops; rays or pixels of the whole step over all ranks)."""
        parts = [(k, self.samplers[k].sample(self.sampler_gens[k], self.device)) for k in self.local]
        return self.steps.forward(model, parts, background, jitter, self.noise_gens, self.world)

    def begin_step(self, model: "SlrfAvatar") -> torch.Tensor | None:
        """Call before `forward`: the occupancy grid of the step's start, for the cross-rank merge in `sync`."""
        if self.distributed and model.cfg.uses_occupancy:
            return model.occupancy.detach().clone()
        return None

    def sync(self, model: "SlrfAvatar", terms: "LossTerms", occupancy_start: torch.Tensor | None, *, stop: bool,
             budget: bool, snapshot: bool) -> StepSync:
        """After `backward`: average the gradients, merge the occupancy grids, agree on the flags (module
        docstring). In one process: the flags as given."""
        if not self.distributed:
            return StepSync(stop=stop, budget=budget, snapshot=snapshot, losses=None)
        import torch.distributed as dist

        params = [p for p in model.parameters() if p.requires_grad]
        dev = params[0].device
        grads = [p.grad.detach().reshape(-1).float() if p.grad is not None else p.new_zeros(p.numel(),
                                                                                               dtype=torch.float32)
                 for p in params]
        had = torch.tensor([p.grad is not None for p in params], dtype=torch.float32, device=dev)
        flags = torch.tensor([stop, budget, snapshot], dtype=torch.float32, device=dev)
        keys = terms.keys()  # the same on every rank (the config)
        losses = torch.stack([getattr(terms, k).detach().float().reshape(()) for k in keys]).to(dev)
        flat = torch.cat(grads + [had, flags, losses])
        dist.all_reduce(flat)
        tail_n = 3 + len(keys)
        had_any = (flat[-tail_n - len(params):-tail_n] > 0).tolist()
        offset = 0
        for p, has in zip(params, had_any):
            n = p.numel()
            p.grad = (flat[offset:offset + n] / self.world).view_as(p).to(p.dtype) if has else None
            offset += n
        if occupancy_start is not None:
            best = changed_values(occupancy_start, model.occupancy)
            dist.all_reduce(best, op=dist.ReduceOp.MAX)
            model.occupancy.copy_(torch.where(best > _UNCHANGED, best, occupancy_start))
        tail = flat[-tail_n:].cpu()
        return StepSync(stop=bool(tail[0] > 0), budget=bool(tail[1] > 0), snapshot=bool(tail[2] > 0),
                        losses={k: float(v) / self.world for k, v in zip(keys, tail[3:].tolist())})

    # ---- generator state (checkpoints) --------------------------------------------------------------------------
    def rng_state(self) -> dict[str, torch.Tensor | int]:
        """Sampler and noise generator states of all S shards (a collective when distributed): "sampler" and
        "noise" are shard 0's (the single-process checkpoint format); with S > 1 also "sampler_shards" and
        "noise_shards" [S, state bytes]."""
        mine = {k: (self.sampler_gens[k].get_state(), self.noise_gens[k].get_state().cpu()) for k in self.local}
        if self.distributed:
            import torch.distributed as dist

            everyone: list = [None] * self.world
            dist.all_gather_object(everyone, mine)
            for d in everyone:
                mine.update(d)
        out: dict[str, torch.Tensor | int] = {"sampler": mine[0][0], "noise": mine[0][1]}
        if self.shards > 1:
            out["sampler_shards"] = torch.stack([mine[k][0] for k in range(self.shards)])
            out["noise_shards"] = torch.stack([mine[k][1] for k in range(self.shards)])
        return out

    def load_rng_state(self, rng: dict, seed: int, step: int) -> bool:
        """Restore this rank's shard generators from a checkpoint's `rng`. When the checkpoint has another number
        of shards (a resume with another --nproc that does not divide them), the shards are new: their generators
        start from `seed` and `step` instead (returns False: the random stream differs from an uninterrupted run)."""
        if saved_shards(rng) != self.shards:
            self.reseed(shard_seed(seed, 7_919 * step))
            return False
        for k in self.local:
            s = rng["sampler_shards"][k] if self.shards > 1 else rng["sampler"]
            n = rng["noise_shards"][k] if self.shards > 1 else rng["noise"]
            self.sampler_gens[k].set_state(s.cpu().clone())  # a row of the stack: own storage (set_state
            self.noise_gens[k].set_state(n.cpu().clone())  # reads from the storage's start)
        return True


def saved_shards(rng: dict) -> int:
    """The number of ray shards a checkpoint's `rng` was written with."""
    return int(rng["sampler_shards"].shape[0]) if "sampler_shards" in rng else 1


def cat_states(states: list["NodeState"], train_counts: list[int]) -> "NodeState":
    """The node states of several shards as one batch. The pose-refinement penalty is a mean over each shard's
    training frames (`train_counts`): their count-weighted mean is the penalty of the whole batch."""
    from avatarctl.model.avatar import NodeState

    def cat(name: str) -> torch.Tensor | None:
        vals = [getattr(s, name) for s in states]
        return None if any(v is None for v in vals) else torch.cat(vals)

    pose = None
    if all(s.pose_penalty is not None for s in states) and sum(train_counts):
        pose = sum(s.pose_penalty * n for s, n in zip(states, train_counts)) / sum(train_counts)
    return NodeState(transforms=cat("transforms"), centers=cat("centers"), delta_n=cat("delta_n"),
                     embed=cat("embed"), mu=cat("mu"), logvar=cat("logvar"), pose_penalty=pose)
