"""The reconstruction methods, one registry: what each is, how it is run and what it takes.

``codedvideo reconstruct --method``, ``reconstruct.method`` in pipeline.yaml, the Python API and the
report all name a method of :data:`REGISTRY`.  The sparse methods (:data:`SPARSE`) sparse-code 7x7xN
patches over tiles (:func:`codedvideo.engine.windows.sparse_volumes`), ``omp`` and ``nonlocal`` with a
dictionary given (:data:`WITH_DICTIONARY`), ``dct`` with the complete 3D DCT; the others are the
classical baselines of :mod:`codedvideo.solvers.baselines`, run with their defaults.  Light: nothing is
imported until a baseline is run (:func:`solver`).
"""

from __future__ import annotations

from dataclasses import dataclass

from codedvideo.model.errors import InputError

@dataclass(frozen=True)
class Method:
    """One reconstruction method."""

    #: Its name (``--method``).
    name: str
    #: Sparse-codes patches over tiles (through the working stores of the cache); else a baseline, whole.
    sparse: bool
    #: Takes a dictionary (``--dictionary``); ``dct`` has its own atoms, the baselines none.
    dictionary: bool
    #: Can adapt its dictionary to each capture (``--adapt``).
    adapts: bool
    #: Its result can be refined (``--refine``: GAP with a low-rank prior on groups, after any method).
    refines: bool
    #: The per-patch solver the sparse methods run (:attr:`codedvideo.solvers.region.OmpSettings.method`), or
    #: the function of :mod:`codedvideo.solvers.baselines` a baseline is.
    solver: str


_METHODS = (
    Method("omp", sparse=True, dictionary=True, adapts=True, refines=True, solver="omp"),
    Method("nonlocal", sparse=True, dictionary=True, adapts=True, refines=True, solver="nonlocal"),
    Method("dct", sparse=True, dictionary=False, adapts=True, refines=True, solver="omp"),
    Method("thinout", sparse=False, dictionary=False, adapts=False, refines=True, solver="thinout"),
    Method("interp", sparse=False, dictionary=False, adapts=False, refines=True, solver="interp"),
    Method("gaptv", sparse=False, dictionary=False, adapts=False, refines=True, solver="gap_tv"),
)

#: Every method by its name, in the order ``--method`` lists them.
REGISTRY: dict[str, Method] = {m.name: m for m in _METHODS}
#: The names of every method, in the order ``--method`` lists them.
METHOD_NAMES = tuple(REGISTRY)
#: The methods that sparse-code patches over tiles.
SPARSE = tuple(m.name for m in _METHODS if m.sparse)
#: The methods that take a dictionary (``--dictionary``; ``reconstruct.method`` in pipeline.yaml).
WITH_DICTIONARY = tuple(m.name for m in _METHODS if m.dictionary)
#: The methods that can adapt their dictionary to each capture (``--adapt``).
ADAPTIVE = tuple(m.name for m in _METHODS if m.adapts)
#: The methods whose result can be refined (``--refine``).
REFINABLE = tuple(m.name for m in _METHODS if m.refines)


def method(name: str) -> Method:
    """The method called ``name``; an :class:`InputError` naming the choices for an unknown one."""
    try:
        return REGISTRY[name]
    except (KeyError, TypeError):
        raise InputError(f"method {name!r}: unknown; choose one of {', '.join(METHOD_NAMES)}") from None


def solver(name: str):
    """The function of :mod:`codedvideo.solvers.baselines` that baseline ``name`` runs (``f(coded, mask)``)."""
    from codedvideo.solvers import baselines

    entry = method(name)
    if entry.sparse:
        raise ValueError(f"method {name}: sparse-codes patches over tiles; it has no whole-capture solver")
    return getattr(baselines, entry.solver)
