"""What the events say about the camera's motion over a packet: one notion of "still", with its reason.

The front-end gives each packet a :class:`Motion`; the back-end refines only windows whose packets measured a
motion (``Motion.still`` false), since a BA fitted to the events of a camera at rest (noise, flicker) moves its
poses.
"""
from __future__ import annotations

import enum


class Motion(enum.Enum):
    """The outcome of a packet. Every member but MOVING gives omega = 0; ``still`` says whether a motion was
    measured at all (over the packet or over its lookback)."""

    MOVING = "moving"  # the packet's events measure a motion: omega by contrast maximisation
    SLOW = "slow"  # flat over the packet, but its lookback (a longer past) measures a motion
    FLAT = "flat"  # the events measure no motion (the score test of omega = 0): the optimum is noise
    UNCONFIRMED = "unconfirmed"  # a motion right after a flat packet that the lookback does not measure
    SPARSE = "sparse"  # too few events around the packet's time to estimate anything (the slicer's rate floor)

    @property
    def still(self) -> bool:
        """No motion measured: the camera counts as at rest here (omega = 0, no BA for a window of such packets)."""
        return self in _STILL

    @property
    def flat(self) -> bool:
        """The packet was estimated but its events measure no motion over it (omega set to 0)."""
        return self in _FLAT


_STILL = frozenset({Motion.FLAT, Motion.UNCONFIRMED, Motion.SPARSE})
_FLAT = frozenset({Motion.SLOW, Motion.FLAT, Motion.UNCONFIRMED})

__all__ = ["Motion"]
