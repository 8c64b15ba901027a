"""Capture and project file formats. Stages read and write files only through these modules."""
