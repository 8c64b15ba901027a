"""Several processes working as one on `torch.distributed` (fit, render and eval with `--nproc N` or `torchrun`).

Two ways in, one `DistEnv`:

- `torchrun --nproc_per_node N [--nnodes M ...] -m avatarctl fit PROJECT ...` (clusters): torchrun starts the
  processes and sets RANK, WORLD_SIZE, LOCAL_RANK, MASTER_ADDR and MASTER_PORT; `DistEnv.from_env()` reads them.
- `avatarctl fit PROJECT --nproc N` (one machine): `launch` spawns N ranks with `torch.multiprocessing`
  (`start_processes`, start method "spawn") and a rendezvous on a free local port; rank 0 sends progress messages
  and its result back to the launching process over a queue.

Backend: NCCL when the ranks train on CUDA, gloo on CPUs. Each rank uses the GPU `LOCAL_RANK`.

Failure and interruption (`launch`): a rank that raises an `AvatarError` sends it to the launcher, which re-raises
it as the one-line error; a rank that dies (killed, out of memory, a crash) makes `join` stop every other rank, and
the launcher raises an `AvatarError` naming the rank and the signal or exit code. Collectives time out after
`timeout_s` (env AVATARCTL_DIST_TIMEOUT, default 600 s) so a rank lost on another machine ends the run instead of
hanging it. Ctrl-C: the terminal sends SIGINT to every process of the foreground group; a rank only notes it
(`stop_requested`), the ranks agree on stopping after the same step and rank 0 writes the checkpoint; a second
Ctrl-C to the launcher terminates the ranks (the last checkpoint stays intact: writes are atomic).
"""

from __future__ import annotations

import contextlib
import os
import queue as queue_mod
import signal
import socket
import threading
from dataclasses import dataclass
from datetime import timedelta
from typing import TYPE_CHECKING, Any, Callable, Iterator

from avatarctl.errors import AvatarError, InputError

if TYPE_CHECKING:
    import torch

ENV_KEYS = ("RANK", "WORLD_SIZE", "LOCAL_RANK", "MASTER_ADDR", "MASTER_PORT")
DEFAULT_TIMEOUT_S = 600.0


@dataclass(frozen=True)
class DistEnv:
    """Where this process stands in a group of `world_size` ranks."""

    rank: int  # 0 .. world_size - 1; rank 0 writes files, logs and records
    world_size: int
    local_rank: int  # rank on this machine: the CUDA device index
    timeout_s: float = DEFAULT_TIMEOUT_S  # collective timeout

    def __post_init__(self) -> None:
        if not (self.world_size >= 1 and 0 <= self.rank < self.world_size and self.local_rank >= 0):
            raise InputError(f"bad distributed environment: rank {self.rank}, world size {self.world_size}, "
                             f"local rank {self.local_rank}", where="RANK / WORLD_SIZE / LOCAL_RANK",
                             fix="launch with torchrun or `--nproc N`")

    @property
    def is_main(self) -> bool:
        return self.rank == 0

    @classmethod
    def from_env(cls) -> "DistEnv | None":
        """The torchrun variables, or None when this process was not started as a rank."""
        if "WORLD_SIZE" not in os.environ:
            return None
        try:
            rank, world = int(os.environ.get("RANK", "0")), int(os.environ["WORLD_SIZE"])
            local = int(os.environ.get("LOCAL_RANK", str(rank)))
            timeout = float(os.environ.get("AVATARCTL_DIST_TIMEOUT", DEFAULT_TIMEOUT_S))
        except ValueError:
            raise InputError("RANK / WORLD_SIZE / LOCAL_RANK / AVATARCTL_DIST_TIMEOUT must be numbers",
                             where="environment", fix="launch with torchrun or `--nproc N`") from None
        return cls(rank=rank, world_size=world, local_rank=local, timeout_s=timeout)


def backend_for(device: "torch.device") -> str:
    return "nccl" if device.type == "cuda" else "gloo"


def rank_device(env: DistEnv | None, device: "torch.device") -> "torch.device":
    """The device of this rank: cuda:LOCAL_RANK for a CUDA run, else `device` unchanged."""
    import torch

    if env is None or device.type != "cuda":
        return device
    if env.local_rank >= torch.cuda.device_count():
        raise InputError(f"local rank {env.local_rank} has no GPU (torch sees {torch.cuda.device_count()})",
                         where="--nproc / --nproc_per_node", fix="start at most one rank per GPU, or --device cpu")
    dev = torch.device("cuda", env.local_rank)
    torch.cuda.set_device(dev)
    return dev


@contextlib.contextmanager
def process_group(env: DistEnv | None, device: "torch.device") -> Iterator[None]:
    """Join the group (env rendezvous: MASTER_ADDR / MASTER_PORT) for the duration; nothing when `env` is None or
    the group is already up (the caller owns it then)."""
    import torch.distributed as dist

    if env is None or dist.is_initialized():
        yield
        return
    missing = [k for k in ("MASTER_ADDR", "MASTER_PORT") if k not in os.environ]
    if missing:
        raise InputError(f"{', '.join(missing)} not set for a distributed run", where="environment",
                         fix="launch with torchrun, or `--nproc N` for one machine")
    dist.init_process_group(backend_for(device), rank=env.rank, world_size=env.world_size,
                            timeout=timedelta(seconds=env.timeout_s))
    try:
        yield
    except BaseException:
        with contextlib.suppress(Exception):  # a peer may be gone: no barrier, just leave
            dist.destroy_process_group()
        raise
    # every rank reaches the end before any tears its connections down: without this barrier a rank leaving first
    # (rank 0 writing its last files later, or finishing sooner) made a gloo peer's threads abort at exit
    # ("terminate called without an active exception", SIGABRT) in about 1 run in 4
    with contextlib.suppress(Exception):
        dist.barrier()
    with contextlib.suppress(Exception):
        dist.destroy_process_group()


def active(env: DistEnv | None) -> bool:
    """True when collectives must be called (a group of more than one rank)."""
    return env is not None and env.world_size > 1


def shard(items: list, env: DistEnv | None) -> list:
    """This rank's share of a work list: items[rank::world_size] (every item to exactly one rank)."""
    return list(items) if env is None else list(items)[env.rank::env.world_size]


def gather_to_main(obj: Any, env: DistEnv | None) -> list[Any] | None:
    """Every rank's `obj` on rank 0 (in rank order); None on the other ranks. One collective."""
    if not active(env):
        return [obj]
    import torch.distributed as dist

    assert env is not None
    out: list[Any] | None = [None] * env.world_size if env.is_main else None
    dist.gather_object(obj, out, dst=0)
    return out


def broadcast_from_main(obj: Any, env: DistEnv | None) -> Any:
    """Rank 0's `obj` on every rank. One collective."""
    if not active(env):
        return obj
    import torch.distributed as dist

    box = [obj]
    dist.broadcast_object_list(box, src=0)
    return box[0]


# ---- signals inside a rank ------------------------------------------------------------------------------------------

@contextlib.contextmanager
def signals_request_stop(flag: Any, signums: tuple[int, ...] = (signal.SIGINT,)) -> Iterator[None]:
    """While inside: each of `signums` only sets `flag` (no KeyboardInterrupt: the ranks must stop after the same
    step, which they agree on; a launcher or torchrun may repeat the signal). Main thread only."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = {s: signal.signal(s, lambda *_: flag.set()) for s in signums}
    try:
        yield
    finally:
        for s, h in previous.items():
            signal.signal(s, h)


# ---- the local launcher -----------------------------------------------------------------------------------------

@dataclass(frozen=True)
class RankChannel:
    """What a spawned rank gets besides its `DistEnv`: a queue to the launcher and the launcher's stop event."""

    queue: Any  # multiprocessing queue: ("progress", payload) | ("result", payload) | ("error", ...)
    stop: Any  # multiprocessing Event: the launcher was interrupted

    def send_progress(self, payload: Any) -> None:
        self.queue.put(("progress", payload))


@dataclass(frozen=True)
class RankFailure:
    """Why a spawned rank ended badly, as the launcher reports it."""

    rank: int
    kind: str  # "error" (an AvatarError), "signal", "crash" (another exception), "lost_peer", "exit"
    message: str
    error: AvatarError | None = None  # kind "error": the rank's error, rebuilt with its class
    traceback: str = ""  # kind "crash": the rank's traceback


class RankCrash(RuntimeError):
    """A rank raised something other than an `AvatarError` (a bug): the message carries its traceback."""


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _rank_main(rank: int, fn: Callable, world: int, port: int, channel: RankChannel, args: tuple) -> None:
    """Entry point of a spawned rank: set the torchrun variables, run `fn(env, channel, *args)`, report."""
    import traceback

    os.environ.update({"RANK": str(rank), "WORLD_SIZE": str(world), "LOCAL_RANK": str(rank),
                       "MASTER_ADDR": "127.0.0.1", "MASTER_PORT": str(port)})
    env = DistEnv.from_env()
    assert env is not None
    code = 0
    try:
        result = fn(env, channel, *args)
        if env.is_main:
            channel.queue.put(("result", result))
    except AvatarError as e:
        channel.queue.put(("error", rank, type(e).__name__, e.what, e.where, e.fix))
        code = 1
    except KeyboardInterrupt:  # Ctrl-C in a stage that does not stop gracefully (render, eval): the launcher says so
        code = 130
    except BaseException as e:  # a lost peer, or a bug: the launcher names the rank
        last = traceback.format_exception_only(type(e), e)[-1].strip().splitlines()[0][:300]
        channel.queue.put(("crash", rank, last, _lost_peer(e), traceback.format_exc()))
        code = 1
    _leave(channel, code)


def _leave(channel: RankChannel, code: int) -> None:
    """End a spawned rank once its messages are delivered (the queue closed, its feeder joined), see `exit_now`."""
    channel.queue.close()
    channel.queue.join_thread()  # the result / error message is in the pipe before the process ends
    exit_now(code)


def exit_now(code: int) -> None:
    """Flush stdio and end the process with `os._exit`, without the interpreter's teardown (as multiprocessing's
    forked workers end). For a rank whose work and files are complete: what the teardown would do is destroy the
    native thread pools of torch / gloo, and there a rank of a finished run occasionally aborted ("terminate called
    without an active exception", SIGABRT: 2 of 6 full test runs for spawned ranks, 1 CI run in about 70 for a
    torchrun rank), which the launcher then reported as a failed run."""
    import sys

    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):
            stream.flush()
    os._exit(code)


def run_as_process(main: Callable[[], None]) -> None:
    """Run a command line's `main` and end the process: through `exit_now` when torchrun started it as a rank
    (WORLD_SIZE set), normally otherwise. The exit status is `main`'s (its SystemExit code, 0 when it returns)."""
    import sys

    if "WORLD_SIZE" not in os.environ:
        main()
        return
    try:
        main()
        code = 0
    except SystemExit as e:
        if isinstance(e.code, str):  # what the interpreter would print for it
            print(e.code, file=sys.stderr)
        code = e.code if isinstance(e.code, int) else int(e.code is not None)
    exit_now(code)


def _lost_peer(e: BaseException) -> bool:
    """A collective failed because another rank is gone (its connection closed, or the timeout passed)."""
    import torch.distributed as dist

    text = str(e).lower()
    return isinstance(e, getattr(dist, "DistError", ())) or any(
        s in text for s in ("connection closed", "connection reset", "timed out", "timeout", "broken pipe"))


def launch(fn: Callable, nproc: int, args: tuple = (), *, on_progress: Callable[[Any], None] | None = None,
           what: str = "run", fix: str = "") -> Any:
    """Run `fn(env, channel, *args)` on `nproc` spawned ranks of one machine and return rank 0's result.

    `fn` must be a module-level function (it is pickled into the spawned processes). Progress payloads that rank 0
    sends go to `on_progress` in this process. Failures become one `AvatarError` (`what` names the run, `fix` says
    how to continue), a bug in a rank a `RankCrash` with its traceback (`_failure` picks the rank to name).
    Ctrl-C: see the module docstring.
    """
    import torch.multiprocessing as mp
    from torch.multiprocessing.spawn import ProcessException

    if nproc < 1:
        raise InputError(f"--nproc must be >= 1, got {nproc}", where="--nproc", fix="e.g. --nproc 2")
    ctx = mp.get_context("spawn")
    channel = RankChannel(queue=ctx.Queue(), stop=ctx.Event())
    messages: list[tuple] = []
    result: list[Any] = []
    presses = {"n": 0}

    def drain(quiet_s: float = 0.0) -> None:
        """Handle the queued messages; with `quiet_s`, until none came for that long (the ranks have ended)."""
        while True:
            try:
                msg = channel.queue.get(timeout=quiet_s) if quiet_s else channel.queue.get_nowait()
            except queue_mod.Empty:
                return
            if msg[0] == "progress":
                if on_progress is not None:
                    on_progress(msg[1])
            elif msg[0] == "result":
                result.append(msg[1])
            else:
                messages.append(msg)

    procs = mp.start_processes(_rank_main, args=(fn, nproc, free_port(), channel, args), nprocs=nproc,
                               join=False, start_method="spawn")

    def on_sigint(signum, frame):  # noqa: ARG001
        presses["n"] += 1
        channel.stop.set()
        if presses["n"] > 1:
            for p in procs.processes:
                if p.is_alive():
                    p.terminate()

    main_thread = threading.current_thread() is threading.main_thread()
    previous = signal.signal(signal.SIGINT, on_sigint) if main_thread else None
    try:
        while True:
            try:
                done = procs.join(timeout=0.2, grace_period=2.0)
            except ProcessException as e:
                drain(quiet_s=0.5)
                if presses["n"]:  # interrupted: the CLI says "interrupted"
                    raise KeyboardInterrupt from None
                codes = [p.exitcode for p in procs.processes]
                raise _failure_error(_failure(e, codes, messages), nproc, what, fix) from None
            drain()
            if done:
                break
        drain(quiet_s=0.5 if not result else 0.0)
    finally:
        if previous is not None:
            signal.signal(signal.SIGINT, previous)
    if not result:
        raise AvatarError(f"{what}: rank 0 ended without a result", fix=fix or "re-run the command")
    return result[0]


def _failure(e: Any, exit_codes: list[int | None], messages: list[tuple]) -> RankFailure:
    """The most telling cause: an AvatarError of a rank, then a rank killed by a signal (other than the SIGTERM
    `join` sends to the survivors), then a crash message (a lost peer shows up as one)."""
    from avatarctl import errors

    found = [m for m in messages if m[0] == "error"]
    if found:
        _, rank, cls, what, where, fix = min(found, key=lambda m: m[1])
        err_cls = getattr(errors, cls, AvatarError)
        err = err_cls(what, where, fix) if isinstance(err_cls, type) and issubclass(err_cls, AvatarError) \
            else AvatarError(what, where, fix)
        return RankFailure(rank, "error", err.one_line(), err)
    for rank, code in enumerate(exit_codes):
        if code is not None and code < 0 and -code != signal.SIGTERM:
            try:
                name = signal.Signals(-code).name
            except ValueError:
                name = f"signal {-code}"
            return RankFailure(rank, "signal", f"was killed by {name}")
    crashes = sorted((m for m in messages if m[0] == "crash"), key=lambda m: (m[3], m[1]))  # bugs before lost peers
    if crashes:
        _, rank, text, lost, tb = crashes[0]
        return RankFailure(rank, "lost_peer" if lost else "crash", f"failed: {text}", traceback=tb)
    code = getattr(e, "exit_code", None)
    return RankFailure(int(getattr(e, "error_index", 0)), "exit", f"exited with code {code}")


def _failure_error(f: RankFailure, nproc: int, what: str, fix: str) -> Exception:
    """A `RankFailure` as the one-line error the CLI prints (an `AvatarError` of a rank is passed on as it is; a
    bug becomes a `RankCrash` with the rank's traceback)."""
    if f.error is not None:
        return f.error
    if f.kind == "crash":
        return RankCrash(f"{what}: rank {f.rank} of {nproc} crashed; its traceback:\n{f.traceback}")
    return AvatarError(f"{what}: rank {f.rank} of {nproc} {f.message}; the other ranks were stopped",
                       fix=fix or "re-run the command")
