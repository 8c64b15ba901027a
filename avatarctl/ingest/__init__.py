"""Ingest stage: a raw capture (EasyMocap, ZJU-MoCap, THuman4.0, PeopleSnapshot, COLMAP) -> a project directory.

`run_ingest(IngestConfig(...))` in `pipeline.py`; readers describe a capture as a `CaptureSource` (`source.py`,
`readers.py`, `avatarctl/io/*`); `undistort.py`, `masks.py` (background matting), `fits.py` (body fits ->
`BodyMotion`), `split.py`, `contact_sheet.py` do one step each. Importing this package loads no heavy library.
"""
