"""Adapting the dictionary to each capture (``--adapt``): K-SVD started from it, on the capture's own first
reconstruction, then the capture reconstructed again with the adapted dictionary."""

from __future__ import annotations

import contextlib
import dataclasses
import time
from pathlib import Path

import numpy as np

from codedvideo.engine.windows import sparse_volumes
from codedvideo.model import doors
from codedvideo.model.errors import InputError
from codedvideo.solvers.dictionaries import KsvdSettings, learn_dictionary

#: Adapting the dictionary to a capture (``--adapt``): K-SVD started from the dictionary, its atoms kept,
#: for this many iterations on this many 7x7xN patches of the capture's own first reconstruction, taken as
#: they are (no rotations, flips or time reversal: they would spread the atoms over motions the scene
#: lacks).  More iterations, patches or atoms a patch gained little for their time, and a dictionary adapted to
#: one capture does not carry to the next, so each gets its own (docs/research.md, "Adapting the dictionary to
#: each capture").
ADAPT_SAMPLES, ADAPT_ITERATIONS, ADAPT_SPARSITY = 7000, 4, 6
#: An atom the capture's patches leave unused is kept in the adaptation of a complete orthonormal basis (the DCT of
#: ``--method dct``, and its adaptations in later rounds), where replacing it with a badly represented patch, as
#: K-SVD does, takes a direction out of the span the next pass needs; a learnt dictionary's is replaced, since
#: keeping them lost there (docs/quality.md, "Adapting the dictionary to each capture").
KEEP_UNUSED = "kept in an orthonormal basis"
#: ``nonlocal --adapt``: the first pass solves the groups of every 7th reference patch (a survey, 0.2 of the
#: groups of the non-local method's stride 3), the second pass the groups of every 4th from the survey's
#: result, with no per-patch tiles (:attr:`codedvideo.engine.parallel.TileWork.first`).  A sparse survey gives
#: the second pass what a full first pass gives, and a second pass of every 4th trades a tenth of a dB for a
#: third of the time (docs/research.md, "Adapting the dictionary to each capture").
ADAPT_SURVEY_STEP, ADAPT_REFINE_STEP = 7, 4
#: ``--adapt-rounds 2`` (``--preset best``): the dictionary adapted again to the second pass's result (K-SVD
#: started from the first adaptation, the same settings), then a third pass with it; the non-local method's
#: third pass solves the groups of every 3rd reference, matched on the second pass's result: the candidate that
#: gained most held out for its time (docs/research.md, "Spending `best`'s time").
ADAPT_LAST_STEP = 3


def adapt_dictionary(volume: np.ndarray, D: np.ndarray, *, seed: int = 0, keep_unused: bool | None = None
                     ) -> tuple[np.ndarray, dict]:
    """``D`` adapted to one capture's first reconstruction ``volume`` (N, H, W), in working units.

    ``keep_unused``: the atoms the capture leaves unused are kept (:data:`KEEP_UNUSED`); None: when ``D`` is an
    orthonormal basis (:func:`is_basis`).  A later round passes the first round's answer.

    A volume with nothing to learn from (flat in space and time) keeps ``D``.
    Returns the dictionary and a record of the adaptation.
    """
    from threadpoolctl import threadpool_limits

    from codedvideo.solvers.dictionaries import prepare_dictionary

    t0 = time.perf_counter()
    first = np.asarray(volume, np.float32)
    if not np.ptp(first) > 1e-3 * max(1.0, float(np.abs(first).max(initial=0.0))):
        return D, dict(adapted=False, reason="the first reconstruction is flat", seconds=time.perf_counter() - t0)
    keep = is_basis(D) if keep_unused is None else keep_unused
    try:
        # one BLAS thread: the same bits whatever the cores (products round otherwise with other thread counts);
        # the caller runs no graph meanwhile, whose own limit would change it midway (adapt_capture)
        with threadpool_limits(limits=1, user_api="blas"):
            Da, meta = learn_dictionary([first], frames=first.shape[0], init=D, seed=seed, settings=KsvdSettings(
                samples=ADAPT_SAMPLES, iterations=ADAPT_ITERATIONS, sparsity=ADAPT_SPARSITY, tol_rms=0.0,
                augment=False, replace_unused=not keep))
    except InputError:  # every patch drawn is flat (a dark frame with a few bright pixels): nothing to learn
        return D, dict(adapted=False, reason="no patch drawn from the first reconstruction has texture",
                       seconds=time.perf_counter() - t0)
    Da = prepare_dictionary(Da, "adapted to the capture")
    return Da, dict(adapted=True, samples=meta["samples"], iterations=ADAPT_ITERATIONS, final_rmse=meta["final_rmse"],
                    unused_atoms="kept" if keep else "replaced", seconds=time.perf_counter() - t0)


def is_basis(D: np.ndarray) -> bool:
    """Whether the dictionary ``D`` (rows, atoms) is a complete orthonormal basis, the DCT of ``--method dct``: as
    many atoms as rows, and ``D^T D v = v`` for a fixed random ``v`` (to float32 rounding); its adaptation keeps the
    atoms a capture leaves unused (:data:`KEEP_UNUSED`)."""
    rows, atoms = D.shape
    if atoms != rows:
        return False
    v = np.random.default_rng(0).standard_normal(atoms)
    D64 = np.asarray(D, np.float64)
    return bool(np.linalg.norm(D64.T @ (D64 @ v) - v) <= 1e-4 * np.linalg.norm(v))


def adapt_capture(job, i: int, stage=None) -> tuple[np.ndarray, str | None, dict | None]:
    """Capture ``i``'s passes before its last (``--adapt``), each a job of its own followed by an adaptation of
    the dictionary to its result (:func:`adapt_dictionary`), the next pass solved with that dictionary.

    One job at a time: no graph is in flight while K-SVD runs (a graph's thread limits BLAS threads, which changed
    an adaptation's bits when it ran beside one).  The passes' warnings (never-open pixels, dependent stops) are
    swallowed: the last job, which gives the result, says them.  ``job``: the prepared job of captures
    (:func:`codedvideo.engine.captures.reconstruct_captures`), of which this reads ``options`` (the dictionary, its
    key, :attr:`~codedvideo.engine.captures.CaptureSettings.execution` and ``config.adapt_rounds``),
    ``pass_settings`` (one per pass; those before the last are run here), ``for_sparse(i)`` (the capture's inputs
    to :func:`codedvideo.engine.windows.sparse_volumes`), ``inputs.count``, ``budget`` and ``survey``: the
    non-local method's passes, each matched on and solved from the previous pass's working store (where the code's
    groups can be solved: ``job.nonlocal_problem(mask)`` is None).  Stops early where a result has nothing to
    learn from.
    ``stage(label, volume, seconds)``: each pass's result (working units) and the capture's seconds to it (its
    passes and adaptations so far), for its error against time.

    Returns the dictionary for the last pass (``dictionary`` itself if none was adapted), the working store the
    last pass is matched on (or None), and the record of the adaptations with the earlier jobs' seconds (or None).
    """
    o, budget = job.options, job.budget
    pass_settings = job.pass_settings[:o.config.adapt_rounds]
    dictionary = o.dictionary
    D_i, store, done, spent = dictionary, None, [], 0.0
    keep = is_basis(dictionary)  # (decided on the dictionary the first round starts from, for every round)
    for k, settings in enumerate(pass_settings):
        with doors.muted():
            pass_job = sparse_volumes(1, lambda _: job.for_sparse(i),
                                      dictionary if k == 0 else (lambda _, D=D_i: (D, "")), settings=settings,
                                      run=dataclasses.replace(o.execution,
                                                              desc=f"pass {k + 1} of {i + 1}/{job.inputs.count}"),
                                      dictionary_key=o.dictionary_key,
                                      first_of=None if store is None else (lambda _, s=store: s))
            with contextlib.closing(pass_job):  # closed here: the graph's thread has ended
                _, first, info = next(pass_job)
        if info is not None:  # (the misfit map is the last pass's, for its still regions)
            info.pop("misfit_taken", None)
        learnt = first is not None and info.get("method") != "static"  # (one pattern for all pixels: no tiles)
        spent += sum(v for v in (info or {}).get("seconds", {}).values() if isinstance(v, (int, float)))
        if stage is not None and first is not None:
            stage(f"pass {k + 1}", first, spent)
        if learnt:
            Da, record = adapt_dictionary(first, D_i, keep_unused=keep)
            done.append((info, record))
            spent += record["seconds"]
            learnt = record["adapted"]  # (a result with nothing to learn from keeps the dictionary)
        del first
        if learnt:
            D_i = Da
            # (a code the groups cannot solve: the survey is the default's result, and the later passes their
            # own per-patch OMP with the adapted dictionary, as with omp --adapt)
            if job.survey and job.nonlocal_problem(job.for_sparse(i)[1]) is None:
                store = info["work_store"]
                if budget is not None:  # the next job reads it: kept until the job ends
                    budget.keep.add(Path(store).absolute())
        if budget is not None and (info or {}).get("work_store"):  # (closed before its window ended)
            budget.finished([info["work_store"]])
        if not learnt:
            break
    if not done:
        return D_i, store, None
    record = dict(done[-1][1], first_pass=dict(seconds=sum(sum(inf["seconds"].values()) for inf, _ in done),
                                               tile_seconds=sum(inf["seconds_total"] for inf, _ in done)))
    if len(pass_settings) > 1:  # each round's K-SVD, and the adaptations' time together
        record.update(rounds=[r for _, r in done], seconds=sum(r["seconds"] for _, r in done),
                      adapted=any(r["adapted"] for _, r in done))
    return D_i, store, record
