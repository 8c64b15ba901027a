"""The Typer command-line interface: parse options -> build a stage config -> run the stage -> print a summary.

No math here, and no torch import at module level (so `avatarctl --help` is instant).
"""
