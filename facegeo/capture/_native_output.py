"""Keeping what native image libraries print on their own off the terminal, and nothing else.

Private to :mod:`facegeo.capture.imageio` (which re-exports :func:`_quiet_native_output` and
:func:`console_stream`): OpenEXR, OpenCV, libpng and libjpeg print warnings while failing on a
corrupt file, past Python, which the :class:`~facegeo.capture.imageio.ImageReadError` raised
already says better. While a read runs, file descriptors 1 and 2 go through pipes drained by one
daemon thread that passes every line on except those matching :data:`_NOISE_PATTERNS` (logged at
DEBUG level on the ``facegeo.capture.imageio`` logger), and ``sys.stdout`` / ``sys.stderr`` hold
only the reading thread's own writes until its read ends; whatever else any thread prints
reaches the terminal. :func:`_quiet_native_output` says how.
"""

from __future__ import annotations

import array
import atexit
import contextlib
import functools
import logging
import os
import re
import sys
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from typing import TextIO

log = logging.getLogger("facegeo.capture.imageio")  # the readers' logger, as before the move

@functools.lru_cache(maxsize=1)
def _libc():
    import ctypes

    return ctypes.CDLL(None)


def _flush_c_stdio() -> None:
    """``fflush(NULL)``: push C stdio buffers (where ``std::cout`` lands) to their fds now."""
    try:
        _libc().fflush(None)
    except Exception:  # pragma: no cover - no C library to ask
        pass


#: What native image libraries print on their own while failing on a file, one pattern per
#: source, searched in each line (``re.search``). Only lines that match are kept off the
#: terminal (and logged at DEBUG level); every other line, from any thread, passes. Checked
#: against OpenEXR 3.5 and the OpenCV 5.0 wheels.
_NOISE_PATTERNS = (
    # OpenEXR core on fd 2: "<file>: (EXR_ERR_BAD_CHUNK_LEADER) Preparing to read scanline ...";
    # the file's path may hold anything (parentheses too); facegeo's own message quoting one
    # ("cannot read OpenEXR ... (truncated or corrupt file: <file>: (EXR_ERR_...") passes
    r"^(?!.*cannot read OpenEXR ).*?: \(EXR_ERR_[A-Z0-9_]+\) ",
    # the OpenEXR Python bindings, through sys.stdout, when the pixel data cannot be decoded
    r"^Warning: Exception raised reading pixel data ",
    # libpng inside OpenCV on fd 2: "libpng error: bad adaptive filter value"
    r"^libpng (?:error|warning): ",
    # libjpeg inside OpenCV on fd 2: "Corrupt JPEG data: 563 extraneous bytes before marker 0xd9"
    r"^(?:Corrupt JPEG data: |Premature end of JPEG file|Invalid SOS parameters for sequential)",
    # OpenCV's image codecs through its logger on fd 2 (libtiff's errors come this way too):
    # "[ WARN:0@0.021] global grfmt_png.cpp:793 readFromStreamOrBuffer PNG input buffer is ..."
    r"^\[ ?(?:WARN|ERROR|INFO):[^\]]*\] (?:\S+ )?(?:grfmt_\w+|loadsave|bitstrm|rgbe|exif)\.cpp:",
)
_NOISE_RE = re.compile("|".join(_NOISE_PATTERNS))
_NOISE_RE_BYTES = re.compile("|".join(_NOISE_PATTERNS).encode())
#: An unfinished line that looks like noise is held for its end up to this many bytes.
_HOLD_MAX = 1 << 16
_CHUNK = 1 << 16
#: How long restoring the descriptors waits at most for the pump to pass on what is in their
#: pipes (normally nothing, or microseconds' worth). Past it, lines printed next can overtake
#: those still in a pipe. It was 0.5 s until a CI run at load ≈ 5 delivered a line's text after
#: its newline (2026-11-24, ``test_prints_of_other_threads_reach_the_real_stdout_in_a_subprocess``,
#: not reproduced in 23 runs since) — more likely the documented race of a ``print`` that
#: fetched the real stream before a read began and wrote its newline after the read ended
#: (:func:`_quiet_native_output`), but a loaded machine can starve the pump too; the wait ends
#: as soon as the pipes are empty, so a longer bound costs nothing while the pump runs.
_DRAIN_TIMEOUT = 5.0
#: Pipes can be waited on with ``selectors`` (not on Windows: sockets only; a thread each there).
_PIPES_SELECTABLE = os.name != "nt"
try:  # POSIX: numbering descriptors, sizing pipes, asking what a pipe holds
    import fcntl as _fcntl
    import termios as _termios
except ImportError:  # pragma: no cover - Windows
    _fcntl = _termios = None

_noise_lock = threading.Lock()
_noise: list[str] = []  # hidden lines not yet logged; logged when the last read ends
_NOISE_KEEP = 1000  # at most this many kept between two logs (the rest counted)
_noise_dropped = 0


def _keep_noise(lines) -> None:
    global _noise_dropped
    with _noise_lock:
        room = max(0, _NOISE_KEEP - len(_noise))
        _noise.extend(lines[:room])
        _noise_dropped += max(0, len(lines) - room)


def _log_noise() -> None:
    global _noise_dropped
    with _noise_lock:
        lines, dropped = _noise[:], _noise_dropped
        _noise.clear()
        _noise_dropped = 0
    text = "\n".join(ln for ln in lines if ln.strip())
    if text or dropped:
        more = f"\n(and {dropped} more lines)" if dropped else ""
        log.debug("native library output hidden: %s%s", text, more)


def _fd_above_std(fd: int) -> int:
    """``fd``, or, when it took the number of a closed standard descriptor (0–2), a
    non-inheritable copy numbered 3 or more (``fd`` is closed): a stdin reader must not find
    our pipe behind descriptor 0, nor a native library's stderr behind 2."""
    if fd > 2 or _fcntl is None:
        return fd
    new = _fcntl.fcntl(fd, _fcntl.F_DUPFD_CLOEXEC, 3)
    os.close(fd)
    return new


def _grow_pipe(fd: int) -> None:
    """Make a pipe hold 1 MiB where the system allows (Linux; 64 KiB otherwise). The pipes are
    drained by a Python thread, which a native call that holds the GIL while it writes more
    than the pipe holds would block on; Python's own writes release the GIL, native image
    decoders write a line or two."""
    try:
        _fcntl.fcntl(fd, _fcntl.F_SETPIPE_SZ, 1 << 20)
    except (AttributeError, OSError):  # not Linux, or above pipe-max-size
        pass


class _Channel:
    """Standard descriptor ``fd``'s pipe: made with the first read, kept for the process.

    While images are read, ``fd`` points at the pipe and the pump passes every line it
    receives on to ``real`` (a duplicate of what ``fd`` pointed at when the redirection began,
    or of an earlier one when that is the same file), unchanged and at once, except lines
    matching :data:`_NOISE_PATTERNS` and an empty line right after one (OpenCV ends its
    messages with two newlines), which are kept for the debug log. An unfinished line is
    passed on as soon as it arrives, unless it looks like noise: then it waits for its end.
    Between reads the pipe idles (what a child process started during a read still writes to
    it is passed on too).
    """

    def __init__(self, fd: int):
        r, w = os.pipe()
        self.read_end, self.write_end = _fd_above_std(r), _fd_above_std(w)
        _grow_pipe(self.write_end)
        st = os.fstat(self.write_end)
        self.pipe_id = (st.st_dev, st.st_ino)
        self.fd = fd
        self.real, self.real_id = -1, None  # where lines go, and its (st_dev, st_ino)
        self.saved = -1  # while redirected: fd as it was, put back by put_back()
        self.lock = threading.Lock()  # held while writing to real, and to replace it
        self.held = b""  # an unfinished line that may be noise
        self.after_noise = False
        self.busy = False  # the pump holds bytes read from the pipe, not yet passed on

    def redirect(self) -> bool:
        """Point ``fd`` at the pipe; False, and nothing done, when ``fd`` is closed."""
        try:
            saved = _fd_above_std(os.dup(self.fd))
        except OSError:
            return False
        try:
            st = os.fstat(saved)
            if (st.st_dev, st.st_ino) == self.pipe_id:
                # fd already points at our pipe: someone saved it during a read and put it back
                # after (the dup / dup2 idiom). Lines keep going where they went, and put_back
                # restores that destination — taking the pipe for one would loop the pump's
                # output back into its own pipe for ever
                os.close(saved)
                saved = _fd_above_std(os.dup(self.real)) if self.real >= 0 else -1
                if saved < 0:
                    return False
            elif (st.st_dev, st.st_ino) != self.real_id:  # a new destination: lines go there
                real = _fd_above_std(os.dup(saved))
                with self.lock:
                    old, self.real, self.real_id = self.real, real, (st.st_dev, st.st_ino)
                if old >= 0:
                    os.close(old)
            os.dup2(self.write_end, self.fd)
        except OSError:
            os.close(saved)
            return False
        self.saved = saved
        return True

    def put_back(self) -> None:
        """Point ``fd`` at what it was, unless someone else redirected it meanwhile (it is no
        longer our pipe); a closed ``fd`` is put back too."""
        saved, self.saved = self.saved, -1
        try:
            st = os.fstat(self.fd)
            if (st.st_dev, st.st_ino) == self.pipe_id:
                os.dup2(saved, self.fd)
        except OSError:
            try:
                os.dup2(saved, self.fd)
            except OSError:  # pragma: no cover
                pass
        finally:
            os.close(saved)

    def idle(self) -> bool | None:
        """True when nothing waits in the pipe nor in the pump; None when it cannot tell (no
        ``FIONREAD``, or a blocking thread reads: Windows)."""
        if _termios is None or not _PIPES_SELECTABLE:
            return None
        n = array.array("i", [0])
        try:
            _fcntl.ioctl(self.read_end, _termios.FIONREAD, n, True)
        except OSError:  # pragma: no cover
            return None
        return n[0] == 0 and not self.busy  # in this order: the pump sets busy, then reads

    def feed(self, chunk: bytes) -> None:
        *lines, tail = (self.held + chunk).split(b"\n")
        self.held = b""
        out, noise = bytearray(), []
        for line in lines:
            if _NOISE_RE_BYTES.search(line) or (self.after_noise and not line.strip()):
                noise.append(line)
                self.after_noise = True
            else:
                out += line + b"\n"
                self.after_noise = False
        if tail:
            if len(tail) < _HOLD_MAX and _NOISE_RE_BYTES.search(tail):
                self.held = tail
            else:
                out += tail
                self.after_noise = False
        if noise:
            _keep_noise([ln.decode("utf-8", "replace") for ln in noise])
        if out:
            self._write(bytes(out))

    def release_held(self) -> None:
        """Log a held unfinished line (it looked like noise and its end did not come)."""
        if self.held:
            _keep_noise([self.held.decode("utf-8", "replace")])
            self.held = b""

    def _write(self, data: bytes) -> None:
        view = memoryview(data)
        with self.lock:
            while view:
                try:
                    view = view[os.write(self.real, view):]
                except BlockingIOError:  # a non-blocking terminal that is full: wait for it
                    time.sleep(0.001)
                except OSError:  # the real destination is gone (closed pipe): as for any writer
                    return

    def drain(self) -> None:
        """Read the pipe for ever, blocking (a thread of its own: where pipes cannot be
        selected on)."""
        while True:
            try:
                chunk = os.read(self.read_end, _CHUNK)
            except OSError:  # pragma: no cover - the pipe broke
                return
            try:
                self.feed(chunk)
            except Exception:  # pragma: no cover - never lose output to a bug in the sorting
                self._write(chunk)


class _Pump:
    """One daemon thread that drains the pipes of fds 1 and 2 as they fill, so a writer never
    blocks on a full pipe nor waits for a line's end. Made with the first read, with the
    pipes; made again in a forked child (its threads are gone)."""

    def __init__(self):
        self.pid = os.getpid()
        self.broken = False  # a pipe failed: the next read makes a new pump
        taken = []  # /dev/null in any closed standard descriptor, so that no descriptor of
        try:  # ours (pipes, epoll's) can take its number
            while (fd := os.open(os.devnull, os.O_RDWR)) <= 2:
                taken.append(fd)
            os.close(fd)
            self.channels = {fd: _Channel(fd) for fd in (1, 2)}
            if _PIPES_SELECTABLE:
                import selectors

                self._sel = selectors.DefaultSelector()
                self._wake_r, self._wake_w = os.pipe()
        finally:
            for fd in taken:
                os.close(fd)
        if not _PIPES_SELECTABLE:
            self.threads = [threading.Thread(target=ch.drain, name="facegeo-native-output",
                                             daemon=True) for ch in self.channels.values()]
            for t in self.threads:
                t.start()
            return
        os.set_blocking(self._wake_r, False)
        os.set_blocking(self._wake_w, False)
        self._sel.register(self._wake_r, selectors.EVENT_READ, None)
        for ch in self.channels.values():
            self._sel.register(ch.read_end, selectors.EVENT_READ, ch)
        self.threads = [threading.Thread(target=self._run, name="facegeo-native-output",
                                         daemon=True)]
        self.threads[0].start()

    def alive(self) -> bool:
        return (self.pid == os.getpid() and not self.broken
                and all(t.is_alive() for t in self.threads))

    def release_held(self) -> None:
        """Have held unfinished lines logged (when the pump next looks)."""
        if _PIPES_SELECTABLE:
            try:
                os.write(self._wake_w, b"\0")
            except BlockingIOError:  # woken already
                pass

    def _run(self) -> None:
        while True:
            for key, _ in self._sel.select():
                ch = key.data
                if ch is None:
                    try:
                        os.read(self._wake_r, 4096)
                    except BlockingIOError:
                        pass
                    for ch in self.channels.values():
                        if ch.idle():
                            ch.release_held()
                    continue
                ch.busy = True
                try:
                    chunk = os.read(ch.read_end, _CHUNK)
                    try:
                        ch.feed(chunk)
                    except Exception:  # pragma: no cover - never lose output to a bug in sorting
                        ch._write(chunk)
                except OSError:  # pragma: no cover - the pipe broke: stop watching it
                    self._sel.unregister(ch.read_end)
                    self.broken = True
                finally:
                    ch.busy = False


_pump: _Pump | None = None


class _ReadingThreadFilter:
    """Stands in for ``sys.stdout`` / ``sys.stderr`` while images are read.

    What a thread writes while it is inside a read (the OpenEXR bindings print their warning
    through ``sys.stdout``) is held until its read ends, then sorted like the descriptors'
    lines (:data:`_NOISE_PATTERNS`); every other thread's writes go straight to the stream
    this replaced, holding ``lock``, which :func:`_restore` holds while it puts the descriptors
    back and waits for the pipes to be drained: text printed then cannot overtake text still
    in a pipe. Anything else is that stream's (``fileno``, ``encoding``, ...), so a reference
    kept after the read keeps working.
    """

    def __init__(self, stream: TextIO):
        self._stream = stream
        self.lock = threading.RLock()  # re-entrant: a signal handler may print

    def write(self, s: str) -> int:
        held = getattr(_reading, "held", None)
        if held is None or not isinstance(s, str):
            with self.lock:
                return self._stream.write(s)
        held.append((self._stream, s))
        return len(s)

    def writelines(self, lines) -> None:
        for s in lines:
            self.write(s)

    def flush(self) -> None:
        if getattr(_reading, "held", None) is None:
            with self.lock:
                self._stream.flush()

    def __getattr__(self, name: str):
        return getattr(self._stream, name)


#: Every stand-in made, by the ``id`` of the stream it stands in for (which it keeps alive):
#: reused, and never freed. CPython 3.11's ``print`` holds ``sys.stdout`` without a reference
#: of its own between writing the text and the newline; freeing a stand-in that another
#: thread has just put away would make it write through a dangling pointer (a crash, seen).
_stand_ins: dict[int, _ReadingThreadFilter] = {}
#: Per thread: ``depth`` of nested reads, and while inside one, ``held``: what it wrote to
#: sys.stdout / sys.stderr, as ``(stream, text)``.
_reading = threading.local()


def _pass_on(held: list) -> None:
    """Sort what a thread wrote during its read: noise lines to the debug log, the rest to the
    stream it was written to, in order."""
    while held:
        stream = held[0][0]
        n = next((i for i, (s, _) in enumerate(held) if s is not stream), len(held))
        text = "".join(t for _, t in held[:n])
        del held[:n]
        keep, noise = [], []
        for line in text.splitlines(keepends=True):
            (noise if _NOISE_RE.search(line.rstrip("\r\n")) else keep).append(line)
        if noise:
            _keep_noise([ln.rstrip("\r\n") for ln in noise])
        if keep:
            try:
                stream.write("".join(keep))
            except Exception:  # pragma: no cover - a closed stream: as for the writer
                pass


@dataclass
class _Window:
    """The redirection while at least one read runs: the channels of the redirected fds, the
    stand-ins installed for sys.stdout / sys.stderr."""

    channels: list[_Channel]
    streams: dict  # {"stdout": _ReadingThreadFilter, ...}

    def saved(self, fd: int) -> int | None:
        """The original of ``fd`` while it is redirected, else None."""
        return next((ch.saved for ch in self.channels if ch.fd == fd), None)


_quiet_lock = threading.Lock()
_quiet_users = 0
_quiet_window: _Window | None = None


def _redirect() -> _Window:
    """Point fds 1 and 2 at their pipes (:class:`_Channel`) and put
    :class:`_ReadingThreadFilter` in front of sys.stdout / sys.stderr. A descriptor that is
    closed is left as it is (nothing written there is seen anyway), as are both when no pipe
    or thread can be had.

    Python's streams are not flushed here nor in :func:`_restore`: text they buffer goes
    through the pipe or straight to the descriptor, either way intact, whereas flushing a
    ``TextIOWrapper`` from a thread other than the one writing to it can reorder its text."""
    global _pump
    channels = []
    try:
        if _pump is None or not _pump.alive():  # first read, or in a forked child
            _pump = _Pump()
        channels = [ch for ch in _pump.channels.values() if ch.redirect()]
    except (OSError, RuntimeError):  # no descriptor, or no thread, to spare
        pass
    streams = {}
    for name in ("stdout", "stderr"):
        stream = getattr(sys, name)
        if stream is not None and not isinstance(stream, _ReadingThreadFilter):
            stand_in = _stand_ins.get(id(stream))
            if stand_in is None:
                stand_in = _stand_ins[id(stream)] = _ReadingThreadFilter(stream)
            setattr(sys, name, stand_in)
            streams[name] = stand_in
    return _Window(channels, streams)


def _restore(window: _Window) -> None:
    """Undo :func:`_redirect`: push C's stdio buffers into the pipes, put the descriptors back
    (not those someone else replaced meanwhile), wait until the pump has passed on what is in
    the pipes, put the streams back, log the noise. Text printed through the stand-ins waits
    meanwhile (their ``lock``), so none of it reaches the terminal before what is still in a
    pipe."""
    with contextlib.ExitStack() as stack:
        for stand_in in window.streams.values():
            stack.enter_context(stand_in.lock)
        if window.channels:
            _flush_c_stdio()
        for ch in window.channels:
            ch.put_back()
        deadline = time.monotonic() + _DRAIN_TIMEOUT
        for ch in window.channels:  # usually idle at once: nothing was written
            while ch.idle() is False and time.monotonic() < deadline:
                time.sleep(0.0002)
            if ch.idle() is False:  # the pump is stuck (its destination does not read)
                log.debug("fd %d: its pipe was not drained in %.1f s; lines printed next may "
                          "come before the ones still in it", ch.fd, _DRAIN_TIMEOUT)
            if ch.held and _pump is not None:
                _pump.release_held()
        for name, stand_in in window.streams.items():
            if getattr(sys, name) is stand_in:
                setattr(sys, name, stand_in._stream)
    _log_noise()


@contextlib.contextmanager
def _quiet_native_output() -> Iterator[None]:
    """Keep what native image libraries print while failing on a file off the terminal (logged
    at DEBUG level), and nothing else.

    The OpenEXR bindings print "Warning: Exception raised reading pixel data ..." through
    Python's ``sys.stdout``, the OpenEXR core library writes "(EXR_ERR_BAD_CHUNK_LEADER) ..."
    to file descriptor 2 past Python, libpng, libjpeg and OpenCV's codecs write to fd 2
    ("libpng error: ...", "[ WARN:0@0.02] global grfmt_png.cpp ..."). The error we raise
    already says what is wrong. While the block runs:

    * fds 1 and 2 point at pipes (made once, kept) that a daemon thread drains as they fill:
      every line passes on to the real descriptor unchanged, except lines matching
      :data:`_NOISE_PATTERNS` (an unfinished line passes at once, unless it looks like noise:
      then it waits for its end);
    * ``sys.stdout`` / ``sys.stderr`` are stand-ins (:class:`_ReadingThreadFilter`) that hold
      what *this* thread writes until the block ends, then sort it the same way; other
      threads' writes go straight through.

    So what other threads print meanwhile (a user's prints, progress bars, child processes)
    reaches the terminal, in order as printed through ``sys.stdout`` / ``sys.stderr``. What
    bypasses them (a native library in another thread, a stream object kept from before the
    read) may land a line out of order around the moment the redirection ends, and stdout
    lines against stderr lines may be ordered differently than written.

    Nested and concurrent uses share one redirection (reference-counted), so threads reading
    images at once are not serialised. The last one out pushes C's stdio buffers into the
    pipes, puts the descriptors back (unless something else replaced them meanwhile:
    ``facegeo``'s own ``/dev/null`` on a broken pipe, say), waits until the pump has passed on
    what is in the pipes (at most :data:`_DRAIN_TIMEOUT`; usually there is nothing), puts the
    streams back and logs the hidden lines. What a child process started meanwhile writes
    later still goes through its pipe and is passed on. A descriptor that is closed is left
    alone. Exceptions pass through, after the same restoration.
    """
    global _quiet_users, _quiet_window
    depth = getattr(_reading, "depth", 0)
    with _quiet_lock:
        if _quiet_users == 0:
            _quiet_window = _redirect()
        _quiet_users += 1
    _reading.depth = depth + 1
    if depth == 0:
        _reading.held = []
    try:
        yield
    finally:
        _reading.depth = depth
        try:
            if depth == 0:
                held, _reading.held = _reading.held, None
                _pass_on(held)
        finally:
            with _quiet_lock:
                _quiet_users -= 1
                if _quiet_users == 0:
                    window, _quiet_window = _quiet_window, None
                    _restore(window)


def console_stream() -> TextIO:
    """A new text stream on the process's real standard error.

    Reads no longer hide what other threads print (:func:`_quiet_native_output` passes every
    line but native libraries' noise on), so ``sys.stderr`` would do; this stream, for the
    progress bars that use it, writes to a duplicate of the real descriptor 2 (the one saved
    while an image is read), past the filtering: no pipe in between, no held line.
    Line-buffered; the caller closes it. Without a usable descriptor 2 (a closed stderr) it
    writes nowhere.
    """
    enc = getattr(sys.__stderr__, "encoding", None) or "utf-8"
    with _quiet_lock:
        saved = _quiet_window.saved(2) if _quiet_window is not None else None
        try:
            fd = os.dup(2 if saved is None else saved)
        except OSError:
            return open(os.devnull, "w", encoding=enc)
    return os.fdopen(fd, "w", buffering=1, encoding=enc, errors="replace")


def _after_fork_in_child() -> None:
    """In a forked child: undo a redirection the parent had open (the child would write into
    the parent's pipe, which nothing in the child drains: its output lost once the parent
    exits, or a writer blocked on the full pipe), close the parent's pipes, and start from no
    redirection with fresh locks (one held by another parent thread at the fork would never be
    released). The child makes its own pump at its first read."""
    global _quiet_users, _quiet_window, _quiet_lock, _pump, _reading, _noise_lock
    window = _quiet_window
    if window is not None:
        for ch in window.channels:
            if ch.saved >= 0:
                try:
                    os.dup2(ch.saved, ch.fd)
                except OSError:  # pragma: no cover
                    pass
        for name, stand_in in window.streams.items():
            if getattr(sys, name) is stand_in:
                setattr(sys, name, stand_in._stream)
    pump = _pump
    if pump is not None:
        fds = [pump._wake_r, pump._wake_w] if hasattr(pump, "_wake_r") else []
        for ch in pump.channels.values():
            fds += [ch.read_end, ch.write_end, ch.real, ch.saved]
        for fd in fds:
            if fd is not None and fd > 2:
                try:
                    os.close(fd)
                except OSError:
                    pass
    _pump = None
    _quiet_users, _quiet_window = 0, None
    _quiet_lock = threading.Lock()
    _noise_lock = threading.Lock()
    _reading = threading.local()


def _at_exit() -> None:
    """At interpreter exit with a read still open (a daemon thread reading, an interrupted
    read): put the descriptors and streams back and let the pump pass on what is in the pipes
    while it still runs (daemon threads stop after the exit handlers), so the last lines
    printed are not left in a pipe."""
    global _quiet_users, _quiet_window
    with _quiet_lock:
        window, _quiet_window = _quiet_window, None
        _quiet_users = 0
        if window is not None:
            _restore(window)


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_after_fork_in_child)
atexit.register(_at_exit)
