"""Frames on Dask: a sequence cut into chunks of frames, each chunk a task on a ``dask.distributed``
cluster (DESIGN.md, "Scale-out").

* ``--workers N`` starts a :class:`distributed.LocalCluster` of N process workers (no dashboard);
  ``--scheduler ADDRESS`` uses a running cluster (``dask scheduler`` / ``dask worker``) instead.
* A chunk is ``--chunk-size`` consecutive frames of the FrameSpec (the last one shorter), rendered by
  :func:`usdml.render.sequence.render_sequence` in the worker. A retried chunk skips the frames a killed
  attempt already wrote in this run (complete files with this run's settings digest, written since the
  run started; older files are rendered again unless ``--resume`` finds them complete with the same
  settings, the test ``--resume`` uses). Files are written under a hidden name and renamed,
  so a worker killed mid-frame leaves no partial file. ``--retries R`` gives every chunk R + 1
  attempts; a worker that dies has its chunk rescheduled by the scheduler on another worker.
* Each worker renders with ``--nthreads`` threads (``USDML_THREADS``, :func:`usdml.parallel.cpu_workers`),
  not the machine's cores.
* Structures built per prototype (voxel arrays, octrees) go through the content-addressed cache on a
  path every worker reads (``USDML_CACHE_DIR``); each is written to a temporary file and renamed, so
  workers that build the same one at once both leave one complete file.
* The result (:class:`usdml.render.result.SequenceResult` with a :class:`~usdml.render.result.DaskRun`):
  frames done (by this run, a killed attempt's included), failed, skipped and stale (``--resume``), each
  failure's message, and a FrameSpec that renders the failed frames again; ``usdml render`` exits non-zero
  when a frame failed.

Frames are the same pixels as a one-process render: a frame depends only on the stage, the settings
and the seed.
"""

from __future__ import annotations

import logging
import os
import sys
import time
import time as _time
from dataclasses import asdict, replace
from typing import NamedTuple

from usdml.errors import UsdmlError, collect_warnings
from usdml.parallel import THREADS_ENV
from usdml.render.result import DaskRun, SequenceResult

log = logging.getLogger("usdml")

__all__ = ["render_on_dask", "chunks", "rerun_spec"]

#: seconds a file's modification time may run behind this machine's clock (a shared file system's
#: server) and still count as written by this run
MTIME_SLACK = 2.0


def chunks(frames: list[float], size: int) -> list[list[float]]:
    """``frames`` in runs of ``size`` (the last run shorter)."""
    size = max(1, int(size))
    return [frames[i:i + size] for i in range(0, len(frames), size)]


def rerun_spec(frames: list[float]) -> str:
    """A FrameSpec of ``frames`` (comma-separated timecodes), for ``--frames``."""
    return ",".join(f"{f:g}" for f in sorted(frames))


class Chunk(NamedTuple):
    """What a task sends back (:func:`render_chunk`)."""

    result: SequenceResult
    seconds: float          #: the chunk's render in the worker
    worker: int             #: the worker's process id


def render_chunk(job: dict, frames: list[float], nthreads: int) -> Chunk:
    """One task: ``frames`` of the job (a :class:`RenderJob` as a dict, ``resume_since`` the run's start)
    in this worker: a retry skips the frames an earlier attempt of this run finished."""
    from usdml.render.sequence import RenderJob, render_sequence

    os.environ[THREADS_ENV] = str(max(1, int(nthreads)))
    rj = RenderJob(**dict(job, frames=[float(f) for f in frames]))
    t0 = _time.perf_counter()
    result = render_sequence(rj)
    return Chunk(result, _time.perf_counter() - t0, os.getpid())


def render_on_dask(job, frames: list[float]) -> SequenceResult:
    """Render ``frames`` of ``job`` (a :class:`usdml.render.sequence.RenderJob` whose stage is a path) on
    Dask (module doc) as its options ``workers``, ``scheduler``, ``chunk_size``, ``retries`` and
    ``nthreads`` say; the result's ``warnings`` are this process's (a worker's stay in its log)."""
    with collect_warnings() as warnings:
        result = _render_on_dask(job, frames)
    return replace(result, warnings=list(warnings))


def _render_on_dask(job, frames: list[float]) -> SequenceResult:
    workers, scheduler, chunk_size, retries, nthreads = (job.workers, job.scheduler, job.chunk_size, job.retries,
                                                         job.nthreads)
    try:
        from distributed import Client, LocalCluster, as_completed
    except ImportError:
        raise UsdmlError("--workers / --scheduler need Dask: pip install 'dask[distributed]'") from None
    if not isinstance(job.stage, (str, os.PathLike)):
        raise UsdmlError("a render on Dask needs the stage as a file every worker can open, not an open Usd.Stage")
    if workers is not None and workers < 1:
        raise UsdmlError(f"--workers {workers}: give 1 or more")
    if chunk_size < 1 or retries < 0:
        raise UsdmlError(f"--chunk-size {chunk_size} / --retries {retries}: give a chunk of 1 or more frames and "
                         "0 or more retries")
    threads = max(1, int(nthreads or max(1, (os.cpu_count() or 1) // max(workers or 1, 1))))
    stage = os.path.abspath(job.stage)
    payload = asdict(replace(job, stage=stage, output=None if job.output is None else os.path.abspath(job.output),
                             single_file=job.single_file or job.frames is None,
                             resume_since=time.time() - MTIME_SLACK))
    started = _time.perf_counter()
    cluster = None
    t0 = _time.perf_counter()
    if scheduler:
        try:
            client = Client(scheduler, timeout="10s")
        except OSError as e:
            raise UsdmlError(f"--scheduler {scheduler}: cannot reach it ({e}); start one with `dask scheduler`") \
                from None
    else:
        cluster = LocalCluster(n_workers=workers or 1, threads_per_worker=1, processes=True,
                               dashboard_address=None, silence_logs=logging.ERROR)
        client = Client(cluster)
    startup = _time.perf_counter() - t0
    print(f"usdml: dask: {len(client.scheduler_info()['workers'])} worker(s) ready in {startup:.1f} s", file=sys.stderr,
          flush=True)
    done, failed, skipped, stale, errors, seconds = [], [], [], [], {}, []
    outputs, previews, skipped_outputs, digests = [], [], [], []
    resolution, visibility = (0, 0), ""
    estimates, lighting = {}, {}
    try:
        futures = {}
        for part in chunks(list(frames), chunk_size):
            fut = client.submit(render_chunk, payload, part, threads, retries=retries, pure=False,
                                key=f"usdml-frames-{rerun_spec(part)}-{os.getpid()}-{id(part)}")
            futures[fut] = part
        for fut in as_completed(futures):
            part = futures[fut]
            try:
                chunk = fut.result()
            except Exception as e:          # the chunk's last attempt failed (or its workers kept dying)
                message = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
                for f in part:
                    errors[f] = message
                    log.warning(f"frame {f:g} failed: {message}")
                failed.extend(part)
                continue
            got = chunk.result
            for f in got.frames:           # a line per frame as chunks come back
                print(f"usdml: frame {f:g} done (worker pid {chunk.worker}, chunk {rerun_spec(part)}, "
                      f"{chunk.seconds:.1f} s)", file=sys.stderr, flush=True)
            # frames a chunk did not render: finished by its earlier attempt in this run (recovered), or
            # (--resume) before the run
            done.extend(got.frames + got.recovered)
            skipped.extend(got.skipped)
            stale.extend(got.stale)
            outputs.extend(got.outputs)
            previews.extend(got.previews)
            skipped_outputs.extend(got.skipped_outputs)
            if got.frames:
                seconds.append(chunk.seconds / len(got.frames))
            resolution, visibility, digests = got.resolution, got.visibility, got.settings_digest
            estimates.update(got.estimates)
            lighting.update(got.lighting_estimates)
    finally:
        client.close()
        if cluster is not None:
            cluster.close()
    order = {f: i for i, f in enumerate(frames)}
    done.sort(key=order.get)
    failed.sort(key=order.get)
    skipped.sort(key=order.get)
    stale.sort(key=order.get)
    run = DaskRun(failed=failed, rerun=rerun_spec(failed) if failed else None, errors=errors,
                  startup_seconds=startup, workers=workers, scheduler=scheduler, chunk_size=chunk_size,
                  retries=retries, threads_per_worker=threads)
    # recovered frames are in ``frames``: a chunk's retry finished them for this run
    return SequenceResult(
        stage=stage, frames=done, skipped=skipped, stale=stale, recovered=[], resolution=resolution,
        seconds_per_frame=(sum(seconds) / len(seconds)) if seconds else 0.0, seconds=_time.perf_counter() - started,
        visibility=visibility, outputs=sorted(outputs), previews=sorted(previews),
        skipped_outputs=sorted(skipped_outputs), settings_digest=digests,
        estimates={f: estimates[f] for f in done if f in estimates},
        lighting_estimates={f: lighting[f] for f in done if f in lighting}, dask=run)
