"""Error types of the ground simulator; all are :class:`protocol.errors.InputError`."""

from __future__ import annotations

from protocol.errors import InputError


class SceneError(InputError):
    """A scene preset or TOML file is missing or invalid."""


class RenderError(InputError):
    """A view cannot be rendered (camera below the terrain, looking at the sky, ...)."""


class TrajectoryError(InputError):
    """A trajectory name or file is invalid."""


class PoseErrorSpecError(InputError):
    """A pose-error specification is invalid."""
