"""The map being built and what works on it: local mapping, the keyframe database
(place recognition, shared by relocalization and loop closing) and loop closing.

A System has one at a time; a re-initialization (tracking lost where there are enough
stereo points) or a loaded map file replaces it (``System._new_map``).
"""

from __future__ import annotations

from dataclasses import dataclass

from .keyframe import KeyFrame
from .keyframe_database import KeyFrameDatabase
from .local_mapping import LocalMapper
from .loop_closing import LoopCloser
from .map import Map
from .vocabulary import Vocabulary


@dataclass
class ActiveMap:
    id: int  # increments at each re-initialization
    map: Map
    mapper: LocalMapper
    kfdb: KeyFrameDatabase
    closer: LoopCloser | None  # None: loop closing off, or localization only

    def place_keyframe(self, kf: KeyFrame, frame_pos: int, vocab: Vocabulary) -> None:
        """A new keyframe goes to loop closing (detection + correction), which adds it to
        the keyframe database; without loop closing straight to the database."""
        if self.closer is not None:
            self.closer.process(kf, frame_pos)
        else:
            self.kfdb.add(kf.id, vocab.transform(kf.desc)[0])

    def collect(self, frame_pos: int, force: bool = False) -> None:
        """Apply the local BA and the loop's full BA that are due at ``frame_pos``."""
        self.mapper.collect(frame_pos, force=force)
        if self.closer is not None:
            self.closer.collect(frame_pos, force=force)

    def shutdown(self) -> None:
        if self.closer is not None:
            self.closer.shutdown()
        self.mapper.shutdown()
