"""`python -m avatarctl` and the `avatarctl` script; torchrun starts its ranks the same way
(`torchrun ... -m avatarctl fit ...`), and a rank ends without the interpreter's teardown (`dist.run_as_process`)."""

from __future__ import annotations


def run() -> None:
    from avatarctl.cli.app import main
    from avatarctl.dist import run_as_process

    run_as_process(main)


if __name__ == "__main__":
    run()
