"""The one predictor loop: rendered frames in, in-between frames out.

A renderer draws every k-th frame. Each rendered frame is ``submit``-ted: the loop keeps the last rendered
frames the predictor needs and runs its ``prepare`` once; each frame in between is a ``predict`` for a target
camera and time, which runs only the predictor's ``render`` on what was prepared. Until enough frames are
rendered (a two-frame method after the first frame, or after ``restart``), the fallback predictor (camera-only
``reproject``) stands in. :class:`engine.runtime.session.Session` (the game-engine API and the server), the
demo and ``interleave eval`` all drive predictors through this loop. A frame's ``motion_vectors`` (the
renderer's, converted by the session) travel with it into the history, where ``mvec`` reads them.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Sequence

from engine.core.frames import Frame
from engine.predict import Prediction, Predictor, PreparedState, Reproject, Target

__all__ = ["Prepared", "PredictionLoop"]


@dataclass
class Prepared:
    """The rendered frames (oldest first), the predictor that prepared them and what it prepared.

    ``fallback`` is None when the loop's own predictor prepared them, else why it did not ("history":
    fewer rendered frames than it needs)."""

    frames: list[Frame]
    predictor: Predictor
    fallback: Optional[str]
    state: PreparedState


class PredictionLoop:
    """Keeps the rendered frames a predictor needs and what it prepared from them.

    Args:
        predictor: the method (``engine.predict.make_predictor``).
        fallback: the method used while fewer frames than ``predictor.history_needed`` are rendered
            (default: camera-only ``reproject``, which needs one).
    """

    def __init__(self, predictor: Predictor, fallback: Optional[Predictor] = None) -> None:
        self.predictor = predictor
        self.fallback = Reproject() if fallback is None else fallback
        if self.fallback.history_needed > 1:
            raise ValueError(f"the fallback '{self.fallback.name}' must need one rendered frame")
        self.prepared: Optional[Prepared] = None

    def restart(self) -> None:
        """Forget every rendered frame (camera cut, time going backwards, a new sequence)."""
        self.prepared = None

    def submit(self, frame: Frame, *, restart: bool = False, predictor: Optional[Predictor] = None) -> Prepared:
        """Add a rendered frame (after the previous one in time) and prepare the predictions that follow it;
        ``restart``: forget the earlier frames first (a camera cut); ``predictor``: the method from this frame
        on (the session's ``auto`` switches between ``mvec`` and ``flow2d``; the kept frames stay). If the
        predictor refuses the frames, the history stays as it was."""
        if predictor is not None:
            self.predictor = predictor
        frames = [frame]
        if self.prepared is not None and not restart:
            keep = max(self.predictor.history_needed, self.predictor.history_wanted, 1)
            frames = (self.prepared.frames + frames)[-keep:]
        return self.load(frames)

    def load(self, frames: Sequence[Frame]) -> Prepared:
        """Replace the history with ``frames`` (oldest first) and prepare them."""
        frames = list(frames)
        if len(frames) >= self.predictor.history_needed:
            predictor, fallback = self.predictor, None
        else:
            predictor, fallback = self.fallback, "history"
        self.prepared = Prepared(frames, predictor, fallback, predictor.prepare(frames))
        return self.prepared

    def predict(self, target: Target) -> Prediction:
        """The frame seen by ``target``'s camera at its time, from what the last ``submit`` prepared."""
        if self.prepared is None:
            raise RuntimeError("predict before any frame was submitted")
        return self.prepared.predictor.render(self.prepared.state, target)
