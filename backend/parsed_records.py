"""Stored JSON records parsed once per change, not once per read.

A fleet's status reports and mission maps are each about 16 KB of JSON (covered rings, POD grid, track),
and validating one costs about 1 ms of CPU (a POD grid's base64 is decoded, every [lat, lon] checked). With
50 vehicles reporting each second, every report read its vehicle's status and map back and every build of
the supervisor page's state read all of them: most of the server's CPU went to parsing the same records
again. The stores keep here, per record, the text last written or read and the model parsed from it: a read
whose text is the one kept returns the kept model (comparing the text is a memcmp; the text read from the
store is still what decides, so another replica's or process's write is parsed as before).

Models handed out are shared between readers: they are values, never changed in place (every update in
the back-end is a `model_copy`).
"""

from __future__ import annotations

import threading
from collections.abc import Hashable
from typing import Generic, TypeVar

from pydantic import BaseModel

M = TypeVar("M", bound=BaseModel)

KEPT_RECORDS = 4096  # per kind: beyond this the oldest kept goes (a fleet is far smaller)


class ParsedRecords(Generic[M]):
    def __init__(self, model: type[M], most: int = KEPT_RECORDS) -> None:
        self._model = model
        self._most = most
        self._kept: dict[Hashable, tuple[str | bytes, M]] = {}
        self._lock = threading.Lock()

    def parsed(self, key: Hashable, text: str | bytes) -> M:
        """The record stored under `key` as `text`: the model kept for that very text, else parsed now."""
        with self._lock:
            kept = self._kept.get(key)
        if kept is not None and kept[0] == text:
            return kept[1]
        model = self._model.model_validate_json(text)
        self.remember(key, text, model)
        return model

    def remember(self, key: Hashable, text: str | bytes, model: M) -> None:
        """`model` was just stored under `key` as `text` (its own JSON): a read of that text needs no parse."""
        with self._lock:
            self._kept.pop(key, None)  # re-inserted last: the oldest are dropped first
            self._kept[key] = (text, model)
            while len(self._kept) > self._most:
                del self._kept[next(iter(self._kept))]

    def forget(self, key: Hashable) -> None:
        with self._lock:
            self._kept.pop(key, None)
