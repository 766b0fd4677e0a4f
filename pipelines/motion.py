"""One notion of "did not move": why a packet or a window counts as still, shared by the front-end and the back-end."""
from __future__ import annotations

from enum import Enum


class Still(str, Enum):
    """Why nothing was estimated or refined: the data hold no motion to measure. A still packet gets omega = 0; a
    still window keeps its initialisation (no BA) and its events enter the map without observation time."""

    NO_MOTION = "the source measured no motion over the window"
