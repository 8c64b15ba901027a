"""The interactive viewer: the render callback (`session`), progressive rendering (`progressive`), and the viser web
server (`server`, the `view` extra). Knows nothing of projects: `stages/view.py` wires a fitted avatar in.
"""
