"""`avatarctl.dist` without processes: the torchrun environment, the work split and which failure the launcher
names (the multi-process behaviour is in test_fit_distributed.py / test_render_eval_distributed.py)."""

from __future__ import annotations

import signal

import pytest

from avatarctl.dist import DistEnv, RankCrash, _failure, _failure_error, shard
from avatarctl.errors import AvatarError, InputError, ProjectError


def test_env_is_read_from_torchrun_variables(monkeypatch):
    for k in ("RANK", "WORLD_SIZE", "LOCAL_RANK", "AVATARCTL_DIST_TIMEOUT"):
        monkeypatch.delenv(k, raising=False)
    assert DistEnv.from_env() is None
    monkeypatch.setenv("WORLD_SIZE", "4")
    monkeypatch.setenv("RANK", "3")
    monkeypatch.setenv("LOCAL_RANK", "1")
    env = DistEnv.from_env()
    assert (env.rank, env.world_size, env.local_rank, env.is_main) == (3, 4, 1, False)
    monkeypatch.setenv("RANK", "4")
    with pytest.raises(InputError, match="rank 4, world size 4"):
        DistEnv.from_env()
    monkeypatch.setenv("RANK", "x")
    with pytest.raises(InputError, match="must be numbers"):
        DistEnv.from_env()


def test_shard_gives_every_item_to_exactly_one_rank():
    items = list(range(10))
    parts = [shard(items, DistEnv(rank=r, world_size=3, local_rank=r)) for r in range(3)]
    assert sorted(sum(parts, [])) == items and parts[0] == [0, 3, 6, 9]
    assert shard(items, None) == items


def test_the_launcher_names_the_most_telling_failure():
    lost = ("crash", 0, "RuntimeError: Connection closed by peer", True, "tb0")
    bug = ("crash", 1, "ZeroDivisionError: division by zero", False, "Traceback ...\nZeroDivisionError")
    err = ("error", 1, "ProjectError", "fit checkpoint not found", "P/fit", "run `avatarctl fit P`")
    killed = [0, -signal.SIGKILL]  # exit codes: rank 1 killed from outside
    # an AvatarError of a rank wins and keeps its class and its one line
    e = _failure_error(_failure(None, killed, [lost, err]), 2, "fit", "resume")
    assert isinstance(e, ProjectError) and e.one_line() == "fit checkpoint not found (P/fit) -> run `avatarctl fit P`"
    # then a rank killed by a signal (not the SIGTERM the launcher sends to the survivors)
    e = _failure_error(_failure(None, killed, [lost]), 2, "fit", "resume with --resume")
    assert isinstance(e, AvatarError) and "rank 1 of 2 was killed by SIGKILL" in e.one_line()
    assert "resume with --resume" in e.one_line()
    # then a bug (with its traceback) before the peers that lost it
    e = _failure_error(_failure(None, [1, -signal.SIGTERM], [lost, bug]), 2, "fit", "")
    assert isinstance(e, RankCrash) and "rank 1 of 2 crashed" in str(e) and "ZeroDivisionError" in str(e)
    # a lost peer alone: a one-line error naming it
    e = _failure_error(_failure(None, [1, 0], [lost]), 2, "fit", "")
    assert isinstance(e, AvatarError) and "rank 0 of 2 failed: RuntimeError: Connection closed" in e.one_line()
