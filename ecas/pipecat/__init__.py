"""Our avatar as a pipecat service (install with the `pipecat` extra): `from ecas.pipecat import AvatarService`."""

from ecas.pipecat.service import AvatarMotionFrame, AvatarService, AvatarStats

__all__ = ["AvatarMotionFrame", "AvatarService", "AvatarStats"]
