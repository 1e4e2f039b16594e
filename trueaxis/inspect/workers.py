"""Process-level speed for ``inspect`` on large clouds: one BLAS thread, and the pictures drawn in a second process.

Neither changes a number of the inspection; both only change where and when the work is done.

One BLAS thread
    The inspection's matrix products are tall and thin ((n, 3) @ (3, k), J^T J with six columns): memory-bound, so a
    second BLAS thread does not make them faster, and on a busy machine it makes them slower by 10-50x (OpenBLAS'
    threads wait for a core each product; measured 0.3-0.4 s instead of 0.006 s for a 1,000,000 x 3 product at load 5 on
    2 cores). :func:`single_blas_thread` sets every OpenBLAS loaded in the process to one thread (through its own
    ``openblas_set_num_threads``, found in the loaded libraries as threadpoolctl finds it) and sets
    ``OPENBLAS_NUM_THREADS=1`` for one loaded later (scipy's own copy), then restores both. The products' values do not
    depend on the thread count (each output element is one dot product, whichever thread computes it).

A figure worker
    matplotlib takes 0.2-0.4 s to import and the pictures of a million-point cloud about 0.5 s to draw; none of it
    needs the fits. :class:`FigureWorker` forks a child process at once that imports matplotlib while the parent reads
    the cloud and computes; the parent sends it each picture's inputs (small: a 15,000-point sample, histogram counts,
    roundness profiles) as soon as they exist and collects the PNG bytes at the end. The child runs the same drawing
    function the parent would (``trueaxis.inspect.report.draw_figure``), so the files are byte for byte the ones drawn
    in-process (a test compares them). Where ``os.fork`` does not exist, or the child fails, the parent draws the
    picture itself.
"""

from __future__ import annotations

import contextlib
import ctypes
import os
import pickle
import struct
import sys
import traceback

__all__ = ["single_blas_thread", "keep_freed_memory", "FigureWorker"]


# ------------------------------------------------------------------------------------------------------- BLAS threads

def _loaded_openblas() -> list[tuple[object, object]]:
    """(set, get) ctypes functions of each OpenBLAS loaded in this process (numpy's and scipy's bundled copies use
    the ``scipy_openblas`` symbol prefix and a ``64_`` suffix)."""
    try:
        with open("/proc/self/maps", encoding="utf-8", errors="replace") as maps:
            paths = {line.split()[-1] for line in maps if "openblas" in line.lower() and "/" in line}
    except OSError:
        return []
    found = []
    for path in sorted(paths):
        try:
            library = ctypes.CDLL(path, mode=os.RTLD_NOLOAD | ctypes.RTLD_GLOBAL)
        except OSError:
            continue
        for prefix in ("scipy_openblas", "openblas"):
            for suffix in ("64_", ""):
                setter = getattr(library, f"{prefix}_set_num_threads{suffix}", None)
                getter = getattr(library, f"{prefix}_get_num_threads{suffix}", None)
                if setter is not None and getter is not None:
                    getter.restype = ctypes.c_int
                    found.append((setter, getter))
                    break
            else:
                continue
            break
    return found


@contextlib.contextmanager
def single_blas_thread():
    """Within the block, BLAS runs on one thread (module docstring); restored after."""
    previous_env = os.environ.get("OPENBLAS_NUM_THREADS")
    os.environ["OPENBLAS_NUM_THREADS"] = "1"
    libraries = _loaded_openblas()
    previous = [int(getter()) for _, getter in libraries]
    for setter, _ in libraries:
        setter(ctypes.c_int(1))
    try:
        yield
    finally:
        for (setter, _), count in zip(libraries, previous):
            setter(ctypes.c_int(count))
        if previous_env is None:
            os.environ.pop("OPENBLAS_NUM_THREADS", None)
        else:
            os.environ["OPENBLAS_NUM_THREADS"] = previous_env


# ------------------------------------------------------------------------------------------------------ the heap

_M_TRIM_THRESHOLD, _M_TOP_PAD, _M_MMAP_THRESHOLD = -1, -2, -3  # glibc's mallopt parameters (malloc.h)


def keep_freed_memory() -> bool:
    """For the rest of this process, glibc's malloc serves blocks up to 32 MB (a million-point coordinate array is
    24 MB) from its heap and keeps freed memory for the next array, instead of mapping fresh pages for every
    temporary array and unmapping them when it is freed (each new page costs a page fault and zeroing): measured today
    on 1,000,000 points, the parent's page faults fell from 120,000 to 57,000 and its CPU time by about 0.2 s. Only
    where each array lives changes, never a value. Returns False where there is no glibc ``mallopt``."""
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
    return all([mallopt(_M_MMAP_THRESHOLD, 32 << 20), mallopt(_M_TRIM_THRESHOLD, 1 << 30),
                mallopt(_M_TOP_PAD, 64 << 20)])


# ------------------------------------------------------------------------------------------------------ figure worker

def _send(fd: int, message) -> None:
    data = pickle.dumps(message, protocol=pickle.HIGHEST_PROTOCOL)
    view = memoryview(struct.pack("<Q", len(data)) + data)
    while view:
        view = view[os.write(fd, view):]


def _receive(fd: int):
    """The next message, or raise EOFError when the other end has closed."""
    def exactly(count):
        chunks, left = [], count
        while left:
            chunk = os.read(fd, min(left, 1 << 20))
            if not chunk:
                raise EOFError
            chunks.append(chunk)
            left -= len(chunk)
        return b"".join(chunks)

    (length,) = struct.unpack("<Q", exactly(8))
    return pickle.loads(exactly(length))


def _child(requests: int, replies: int) -> None:
    """The worker's life: import the drawing code (matplotlib), then draw each request until the pipe closes."""
    status = 0
    try:
        from .report import draw_figure, warm_up_drawing

        warm_up_drawing()
        while True:
            try:
                inputs = _receive(requests)
            except EOFError:
                break
            try:
                _send(replies, ("ok", draw_figure(inputs)))
            except Exception:  # noqa: BLE001 - reported to the parent, which draws the picture itself
                _send(replies, ("error", traceback.format_exc()))
    except BaseException:  # noqa: BLE001 - a child must never return into the parent's code
        status = 1
    finally:
        os._exit(status)


class FigureWorker:
    """Pictures drawn in a forked child process (module docstring). Use as a context manager::

        with FigureWorker() as worker:
            worker.submit(inputs)          # as soon as a picture's inputs exist
            ...
            results = worker.results()     # [(png bytes, caption, data)] in the order submitted

    ``draw`` is the in-process fallback (``trueaxis.inspect.report.draw_figure``), used for every picture when the
    child could not be started and for a picture the child failed to draw.
    """

    def __init__(self, start: bool = True):
        self._pid = None
        self._requests = self._replies = None
        self._sender = None  # one thread writes the requests: the parent never waits for the child to read
        self._pending: list = []
        self.failures: list[str] = []
        if start and hasattr(os, "fork"):
            self._start()

    @property
    def running(self) -> bool:
        return self._pid is not None

    def _start(self) -> None:
        request_read, request_write = os.pipe()
        reply_read, reply_write = os.pipe()
        sys.stdout.flush()
        sys.stderr.flush()
        pid = os.fork()
        if pid == 0:  # the child: never returns
            os.close(request_write)
            os.close(reply_read)
            _child(request_read, reply_write)
        os.close(request_read)
        os.close(reply_write)
        self._pid, self._requests, self._replies = pid, request_write, reply_read

    def submit(self, inputs: dict) -> None:
        """Queue one picture (a dict for ``draw_figure``)."""
        if self.running:
            if self._sender is None:
                from concurrent.futures import ThreadPoolExecutor

                self._sender = ThreadPoolExecutor(max_workers=1)
            # a request larger than the pipe's buffer would block until the child reads it, and the child reads
            # only once matplotlib is imported: the writing is the sender thread's (os.write releases the GIL)
            self._sender.submit(_send, self._requests, inputs)
            self._pending.append((inputs, True))
            return
        self._pending.append((inputs, False))

    def results(self) -> list:
        """[(png bytes, caption, data)] of every picture submitted, in order; the queue is emptied."""
        from .report import draw_figure

        out = []
        for inputs, sent in self._pending:
            result = None
            if sent and self.running:
                try:
                    status, value = _receive(self._replies)
                    if status == "ok":
                        result = value
                    else:
                        self.failures.append(value)
                except (EOFError, OSError):
                    self.failures.append("the figure process ended unexpectedly")
                    self._stop()
            out.append(result if result is not None else draw_figure(inputs))
        self._pending = []
        return out

    def _stop(self) -> None:
        if self._pid is None:
            return
        # replies first: a child busy drawing then fails to answer and exits, which ends a send in progress
        # (EPIPE); only then is the request pipe closed (never under the sender's feet), and the child reaped
        with contextlib.suppress(OSError):
            os.close(self._replies)
        if self._sender is not None:
            self._sender.shutdown(wait=True, cancel_futures=True)
            self._sender = None
        with contextlib.suppress(OSError):
            os.close(self._requests)
        with contextlib.suppress(ChildProcessError):
            os.waitpid(self._pid, 0)
        self._pid = self._requests = self._replies = None

    def close(self) -> None:
        """End the child (it exits when its request pipe closes) and reap it."""
        self._pending = []
        self._stop()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
        return False
