"""The stages: one module per command, each `run(project, config, progress) -> typed result`.

    synth -> ingest -> fit -> render -> evaluate   (demo runs them all on a synthetic capture)

A stage opens the project, resolves its config, calls the libraries below it (`ingest/`, `fit/`, `render/`,
`evaluate/`, `synth/`, `model/`, `io/`, `body/`), writes its outputs atomically and records itself in the manifest.
Every stage reports one progress shape, `avatarctl.progress.ProgressReport` (the libraries send it too). What several
stages share lives in `common.py`; a stage never imports another stage's module (the demo excepted: it is the chain). Only `avatarctl.cli` imports stages.
"""
