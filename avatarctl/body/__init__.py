"""Body models behind one interface (`BodyModel`): anny (free default), SMPL and SMPL-X from a user file.

Use `load_body_model(name, path)`; nothing here is imported at package import time.
"""
