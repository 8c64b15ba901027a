"""Ingest library: a raw capture (EasyMocap, ZJU-MoCap, THuman4.0, PeopleSnapshot, COLMAP) -> a project directory.

`run_ingest(IngestConfig(...))` in `pipeline.py` (called by `avatarctl.stages.ingest`); the readers (`readers.py`,
`avatarctl/io/*`) describe a capture as a `CaptureSource` (the reader contract, `avatarctl/io/capture.py`);
`undistort.py`, `masks.py` (background matting), `fits.py` (body fits -> `BodyMotion`), `split.py`,
`contact_sheet.py` do one step each. Importing this package loads no heavy library.
"""
