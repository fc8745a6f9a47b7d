"""The one exception the OctoMap readers raise for bad input."""

from __future__ import annotations

__all__ = ["MapFormatError", "MapTooLargeError"]


class MapFormatError(ValueError):
    """A ``.bt`` / ``.ot`` file or message payload that is not a valid OctoMap octree.

    Raised for truncated, corrupt or wrong-header data, a node count that does not match the
    header, an unsupported tree id, or unexpected trailing bytes. The message names the
    source (a path, or ``"<bytes>"`` for in-memory data) and the byte offset where reading
    failed; both are also attributes.

    Attributes:
      source: the path or ``"<bytes>"``.
      offset: byte offset into the file / payload (``None`` when not tied to one byte).
      reason: the message without source and offset.
    """

    def __init__(self, source, offset: int | None, reason: str):
        self.source = str(source)
        self.offset = None if offset is None else int(offset)
        self.reason = reason
        where = self.source if self.offset is None else f"{self.source}: byte {self.offset}"
        super().__init__(f"{where}: {reason}")

    def __reduce__(self):  # picklable across processes
        return (type(self), (self.source, self.offset, self.reason))


class MapTooLargeError(MapFormatError):
    """A valid octree with more leaves than the reader's ``max_leaves`` limit (a
    ``MapFormatError``, so callers that handle bad files handle it too)."""
