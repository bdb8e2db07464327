"""The one UserError of the four commands lives in schemas/errors.py (training may import only
schemas); re-exported here for training's modules."""

from schemas.errors import UserError  # noqa: F401
