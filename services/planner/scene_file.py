"""The planning scene on disk, so that a planner that crashed and was restarted plans around the
objects its clients added, as if it had never gone.

The file holds the scene as the `planner/scene` requests that rebuild it (one `add` of every world
object, then one `attach` per attached object, posed in its link's frame) and the revision, as a
msgpack map in the wire encoding:

    {v: 1, revision: int, requests: [SceneRequest, ...]}

so loading goes through the same validation as a client's request. It is replaced atomically
(written beside it, then renamed) after every change; a file that cannot be read is moved aside
(`.unreadable`) and the planner starts with an empty scene.
"""

from __future__ import annotations

import dataclasses
import logging
import os
from collections.abc import Sequence
from pathlib import Path

import msgpack

from robonav.pipeline.collision.attached import AttachedObject
from robonav.pipeline.scene import SceneObject
from robonav.pipeline.wire.codec import SCHEMA_VERSION, unpack
from robonav.pipeline.wire.messages import SceneRequest
from robonav.services.planner.scene_specs import object_spec

log = logging.getLogger("robonav.planner.scene")


def scene_requests(world_objects: Sequence[SceneObject], attached: Sequence[AttachedObject]) -> list[SceneRequest]:
    """The requests that rebuild a scene on an empty planner, in order."""
    requests = []
    if world_objects:
        requests.append(SceneRequest(operation="add", objects=tuple(object_spec(o) for o in world_objects)))
    for a in attached:  # its pose is link_from_object: attach it in the link's frame, no robot state needed
        requests.append(SceneRequest(operation="attach", link=a.link, touch_links=tuple(a.touch_links),
                                     objects=(dataclasses.replace(object_spec(a.object), frame_id=a.link),)))
    return requests


class SceneFile:
    """Where one planner keeps its scene."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self._write_failed = False

    def save(self, revision: int, requests: Sequence[SceneRequest]) -> None:
        """Replace the file; a failure is logged (once until a write succeeds again), never raised:
        the scene change itself has been applied."""
        data = msgpack.packb({"v": SCHEMA_VERSION, "revision": revision, "requests": [r.to_dict() for r in requests]},
                             use_bin_type=True)
        partial = self.path.with_name(f".{self.path.name}.{os.getpid()}.partial")
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            with open(partial, "wb") as out:
                out.write(data)
                out.flush()
                os.fsync(out.fileno())
            os.replace(partial, self.path)
        except OSError as exc:
            if not self._write_failed:
                log.error("cannot save the planning scene to %s: %s; a restarted planner would start without it",
                          self.path, exc)
            self._write_failed = True
            return
        if self._write_failed:
            log.info("planning scene saved to %s again", self.path)
        self._write_failed = False

    def load(self) -> tuple[int, list[SceneRequest]] | None:
        """(revision, requests) from the file; None when there is none or it cannot be read."""
        try:
            raw = self.path.read_bytes()
        except FileNotFoundError:
            return None
        except OSError as exc:
            log.error("cannot read the planning scene %s: %s; starting with an empty scene", self.path, exc)
            return None
        try:
            data = unpack(raw)
            if not isinstance(data, dict) or data.get("v") != SCHEMA_VERSION or not isinstance(data.get("revision"), int) \
                    or not isinstance(data.get("requests"), list):
                raise ValueError("not a planning scene file of this version")
            return data["revision"], [SceneRequest.from_dict(r) for r in data["requests"]]
        except ValueError as exc:  # ProtocolError is one
            aside = self.path.with_name(self.path.name + ".unreadable")
            log.error("the planning scene %s is unreadable (%s); moved to %s, starting with an empty scene",
                      self.path, exc, aside)
            try:
                os.replace(self.path, aside)
            except OSError:
                pass
            return None
