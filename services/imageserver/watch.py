"""The ``watch`` source: frames as an SEM's own software saves them into a folder.

Most SEM software can save every new frame to a folder; following that folder is the
adapter that works with any instrument. The folder is watched with the ``watchdog``
library (inotify on Linux, its polling observer elsewhere or when asked), and scanned
again every second in case an event was missed.

A file is published once it is **complete**:

* closed after writing (inotify's close-write), or renamed into the folder (a rename
  is atomic), or, where no such event comes (polling, network shares), unchanged in
  size and modification time for ``settle_s``;
* and readable as a whole image (a TIFF whose strips end past the end of the file is
  still being written), and unchanged while it was read (a last chunk landing during
  the read would otherwise make the file a "new" one later: an old frame published
  again).

Frames go out **in the order their files appeared** (files that appear together, in one
poll, in name order), each **once**: a file is known by
its device, inode, size and modification time, so a frame renamed after it was
published is not published again, while a file rewritten in place is a new frame.
Files that are deleted before they are read, that are not images, or that stay
unreadable (unchanged for a second and still not an image; a file that looks unfinished,
cut short and not closed, for ``give_up_s``) are logged, counted (``files_*`` in health)
and skipped; a file that never completes holds the ones after it for ``give_up_s`` at most.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import OrderedDict
from dataclasses import dataclass, field
from pathlib import Path

from watchdog.events import FileSystemEvent, FileSystemEventHandler
from watchdog.observers import Observer
from watchdog.observers.polling import PollingObserver

from semservo.imagefiles import IMAGE_SUFFIXES, DataBar, ImageFileError, read_sem_image
from semservo.instruments import AcquiredImage, NotReady
from services.imageserver.sources import merge_metadata

log = logging.getLogger("imageserver.watch")
# A file being written is read many times before it is whole: tifffile would warn at
# each try ("invalid offset to first page", fifty a second); this module says once what
# became of the file.
logging.getLogger("tifffile").setLevel(logging.ERROR)

#: How often the folder is listed again, whatever the events say.
RESCAN_S = 1.0
#: How many published (and skipped) files are remembered, to never publish one twice.
REMEMBERED = 100_000
#: A complete-looking file still unreadable after this long unchanged is skipped.
UNREADABLE_AFTER_S = 1.0
#: Files that appear within this long of each other arrived together (one poll of the
#: folder, one burst of events): they go out in name order.
SAME_BATCH_S = 0.05
#: How often a pending file (being written, or settling) is looked at again.
PENDING_CHECK_S = 0.02


def looks_unfinished(reason: str) -> bool:
    """Whether a file's read failed as a file still being written fails: pixel data past
    its end, no page yet (an index written last), a PNG cut short."""
    return any(sign in reason for sign in ("truncated", "no page 0", "broken PNG", "unexpected end"))


@dataclass
class Candidate:
    """A file seen in the folder and not yet published or skipped."""

    path: Path
    first_seen_ns: int
    order: tuple[int, str]  # (batch of arrival, name): files seen together go in name order
    closed: bool = False  # a close-write or rename-in event came after the last change
    last_signature: tuple[int, int] | None = None  # (size, mtime_ns)
    stable_since: float = field(default_factory=time.monotonic)
    unreadable: str | None = None


class _Events(FileSystemEventHandler):
    """watchdog's thread hands every event to the source (kept short: it only notes)."""

    def __init__(self, source: "WatchSource"):
        self.source = source

    def on_any_event(self, event: FileSystemEvent) -> None:
        if event.is_directory:
            return
        if event.event_type == "moved":
            self.source.note(Path(str(event.src_path)), gone=True)
            self.source.note(Path(str(event.dest_path)), closed=True)
        elif event.event_type == "deleted":
            self.source.note(Path(str(event.src_path)), gone=True)
        elif event.event_type in ("created", "modified"):
            self.source.note(Path(str(event.src_path)), changed=True)
        elif event.event_type == "closed":
            self.source.note(Path(str(event.src_path)), closed=True)


class WatchSource:
    """Frames from files appearing in ``folder`` (see the module's docstring)."""

    name = "watch"
    #: Every complete file is published as it comes (no frame rate of its own).
    paced = False
    #: An SEM that saves nothing for a while is not scanning: not a frozen source.
    idle_is_normal = True

    def __init__(
        self,
        folder: str | Path,
        *,
        pattern: str = "*",
        existing: bool = False,
        settle_s: float = 0.3,
        give_up_s: float = 10.0,
        polling: bool = False,
        overrides: dict | None = None,
        fallbacks: dict | None = None,
        data_bar: DataBar = "auto",
        clock=time.monotonic,
        notify=None,
    ):
        self.folder = Path(folder)
        #: Told (from watchdog's thread) when something happened in the folder: the image
        #: server then looks, instead of asking again and again.
        self.notify = notify or (lambda: None)
        if not self.folder.is_dir():
            raise FileNotFoundError(f"no folder to watch at {self.folder}")
        self.pattern = pattern
        self.settle_s = settle_s
        self.give_up_s = give_up_s
        self.overrides = {key: value for key, value in (overrides or {}).items() if value is not None}
        self.fallbacks = {key: value for key, value in (fallbacks or {}).items() if value is not None}
        self.data_bar = data_bar
        #: The data bar detection found on the first file of each shape, kept for the rest.
        self.detected_bars: dict[tuple[int, ...], int] = {}
        self.clock = clock
        self.counters = {"files_published": 0, "files_skipped": 0, "files_vanished": 0, "files_ignored": 0,
                         "files_renamed": 0}
        self.last_skipped: str | None = None
        self.last_published_at: float | None = None  # on ``clock``
        self._lock = threading.Lock()
        self._candidates: dict[Path, Candidate] = {}
        self._published: OrderedDict[tuple, str] = OrderedDict()  # identity -> name, to never publish twice
        self._skipped: OrderedDict[tuple, str] = OrderedDict()  # identity -> reason, to not retry unchanged
        self._seen_at_start: set[Path] = set()
        self._ignored: set[Path] = set()
        self._batch = 0
        self._last_arrival = -1e9
        self._next_rescan = 0.0
        if existing:
            for path in sorted(self._listing()):
                self.note(path, changed=True)
        else:
            self._seen_at_start = set(self._listing())
            if self._seen_at_start:
                log.info("watching %s: %d files already there are not frames of this session (watch_existing "
                         "publishes them)", self.folder, len(self._seen_at_start))
        self.observer = PollingObserver(timeout=0.1) if polling else Observer(timeout=0.05)
        self.observer.schedule(_Events(self), str(self.folder), recursive=False)
        self.observer.start()
        self.mode = "polling" if polling else type(self.observer).__name__.replace("Observer", "").lower() or "native"

    # -- what the folder holds -------------------------------------------------------------
    def _listing(self) -> list[Path]:
        return [path for path in self.folder.glob(self.pattern) if path.is_file()]

    def _wanted(self, path: Path) -> bool:
        return path.parent == self.folder and path.match(self.pattern)

    def note(self, path: Path, *, changed: bool = False, closed: bool = False, gone: bool = False) -> None:
        """Record an event about ``path`` (from watchdog's thread or a rescan)."""
        if not self._wanted(path):
            return
        with self._lock:
            candidate = self._candidates.get(path)
            if gone:
                if candidate is not None:
                    del self._candidates[path]
                    self.counters["files_vanished"] += 1
                    log.info("%s went away before it was complete (deleted or renamed)", path.name)
                self._seen_at_start.discard(path)
                return
            if path in self._seen_at_start:
                if not (changed or closed):
                    return
                self._seen_at_start.discard(path)  # rewritten since: a new frame
            if candidate is None:
                if path.suffix.lower() not in IMAGE_SUFFIXES:
                    if path not in self._ignored:  # counted once, however many events it makes
                        if len(self._ignored) > REMEMBERED:
                            self._ignored.clear()
                        self._ignored.add(path)
                        self.counters["files_ignored"] += 1
                        log.debug("ignoring %s: not a PNG or TIFF", path.name)
                    return
                now = self.clock()
                if now - self._last_arrival > SAME_BATCH_S:  # a poll (or a burst) reports several at once
                    self._batch += 1
                self._last_arrival = now
                candidate = Candidate(path, time.time_ns(), (self._batch, path.name), stable_since=now)
                self._candidates[path] = candidate
            if closed:
                candidate.closed = True
            elif changed:
                candidate.closed = False
                candidate.stable_since = self.clock()
        self.notify()

    def _rescan(self) -> None:
        """List the folder: events can be missed (an overflowing queue, a network share)."""
        present = set(self._listing())
        with self._lock:
            known = set(self._candidates)
        for path in present - known - self._seen_at_start:
            if path.suffix.lower() in IMAGE_SUFFIXES and not self._is_done(path):
                self.note(path, changed=True)
        for path in known - present:
            self.note(path, gone=True)

    def _is_done(self, path: Path) -> bool:
        """Published or skipped as it is now (a change makes it a new file)."""
        try:
            identity = self._identity(path)
        except OSError:
            return False
        return identity in self._published or identity in self._skipped

    @staticmethod
    def _identity(path: Path) -> tuple:
        stat = path.stat()
        return (stat.st_dev, stat.st_ino, stat.st_size, stat.st_mtime_ns)

    # -- the source interface -------------------------------------------------------------
    def acquire(self) -> AcquiredImage:
        """The next complete frame, in the order the files appeared; :class:`NotReady`
        when none is complete yet. Never blocks for long: one file is read at most."""
        now = self.clock()
        if now >= self._next_rescan:
            self._next_rescan = now + RESCAN_S
            self._rescan()
        with self._lock:
            waiting = sorted(self._candidates.values(), key=lambda candidate: candidate.order)
        for candidate in waiting[1:]:  # every file's settle timer runs, not only the first's
            self._observe(candidate, now)
        for candidate in waiting:
            image = self._try(candidate, now)
            if image is not None:
                return image
            if candidate.path in self._candidates and now - candidate.stable_since < self.give_up_s:
                break  # an earlier file still being written holds the later ones (order)
        raise NotReady

    def wake_in_s(self) -> float:
        """When :meth:`acquire` should be asked again without an event: soon while a file
        is pending (its settle timer, and a write that made no event), else at the next
        rescan of the folder."""
        now = self.clock()
        with self._lock:
            pending = bool(self._candidates)
        if pending:
            return min(PENDING_CHECK_S, max(self.settle_s / 3, 0.005))
        return max(self._next_rescan - now, 0.0)

    def _observe(self, candidate: Candidate, now: float):
        """The file's stat now, its settle timer restarted if it changed; None if gone."""
        try:
            stat = candidate.path.stat()
        except FileNotFoundError:
            self.note(candidate.path, gone=True)
            return None
        signature = (stat.st_size, stat.st_mtime_ns)
        if signature != candidate.last_signature:
            candidate.last_signature = signature
            if not candidate.closed:
                candidate.stable_since = now
        return stat

    def _try(self, candidate: Candidate, now: float) -> AcquiredImage | None:
        """Publish, skip or keep waiting for one candidate."""
        path = candidate.path
        stat = self._observe(candidate, now)
        if stat is None:
            return None
        settled = now - candidate.stable_since >= self.settle_s
        if not (candidate.closed or settled):
            return None
        identity = (stat.st_dev, stat.st_ino, stat.st_size, stat.st_mtime_ns)
        given_up = now - candidate.stable_since >= max(2 * self.settle_s, UNREADABLE_AFTER_S)
        if stat.st_size == 0:  # created, not written yet; or never will be
            if given_up:
                self._skip(candidate, identity, "empty file")
            return None
        if identity in self._skipped:  # unchanged since it was found unreadable
            self._forget(candidate)
            return None
        if identity in self._published:
            self._forget(candidate)
            self.counters["files_renamed"] += 1
            log.info("%s is %s renamed: already published", path.name, self._published[identity])
            return None
        try:
            image = read_sem_image(path, data_bar=self.data_bar, detected=self.detected_bars)
            after = path.stat()
        except FileNotFoundError:
            self.note(path, gone=True)
            return None
        except (ImageFileError, OSError) as error:
            candidate.unreadable = str(error)
            # Unchanged for a while and still unreadable: not an image we can use. But a
            # file that looks unfinished and was not closed may be a writer pausing (a slow
            # share, a TIFF whose index comes last): it waits up to give_up_s, holding the
            # files after it, instead of being skipped after a second and published out of
            # order when its last chunk lands.
            unfinished = not candidate.closed and looks_unfinished(str(error))
            if now - candidate.stable_since >= (self.give_up_s if unfinished else
                                                max(2 * self.settle_s, UNREADABLE_AFTER_S)):
                self._skip(candidate, identity, str(error))
            return None
        if (after.st_dev, after.st_ino, after.st_size, after.st_mtime_ns) != identity:
            # Written to while it was read: what was read may mix two versions, and the
            # file published under its old identity would come back as new (a stale
            # frame, published again after a move). Wait for it to settle.
            candidate.closed = False
            candidate.stable_since = now
            candidate.last_signature = (after.st_size, after.st_mtime_ns)
            return None
        self._forget(candidate)
        self._published[identity] = path.name
        while len(self._published) > REMEMBERED:
            self._published.popitem(last=False)
        self.counters["files_published"] += 1
        self.last_published_at = now
        metadata = merge_metadata(image.metadata.updated(data_bar_rows=image.data_bar_rows or None),
                                  self.overrides, self.fallbacks, image.pixels.shape[1])
        image.pixels.setflags(write=False)
        frame_ns = image.pixels.size * metadata["dwell_ns"] if metadata.get("dwell_ns") else None
        return AcquiredImage(
            pixels=image.pixels, acquired_at_ns=stat.st_mtime_ns, label=path.name,
            # The scan ended before the file appeared; it took rows x columns x dwell.
            scan_started_at_ns=int(candidate.first_seen_ns - frame_ns) if frame_ns else None,
            **metadata,
        )

    def _forget(self, candidate: Candidate) -> None:
        with self._lock:
            self._candidates.pop(candidate.path, None)

    def _skip(self, candidate: Candidate, identity: tuple, reason: str) -> None:
        self._forget(candidate)
        self._skipped[identity] = reason
        while len(self._skipped) > REMEMBERED:
            self._skipped.popitem(last=False)
        self.counters["files_skipped"] += 1
        self.last_skipped = f"skipped {candidate.path.name}: {reason}"
        log.warning("%s", self.last_skipped)

    def describe(self) -> dict:
        with self._lock:
            pending = len(self._candidates)
        since = None if self.last_published_at is None else round(self.clock() - self.last_published_at, 3)
        return {"source": self.name, "folder": str(self.folder), "pattern": self.pattern, "mode": self.mode,
                "pending": pending, "last_skipped": self.last_skipped, "since_last_frame_s": since, **self.counters}

    def close(self) -> None:
        self.observer.stop()
        self.observer.join(timeout=5)

