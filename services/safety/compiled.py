"""Calling compiled (numba) kernels without numba's per-call type dispatch."""

from __future__ import annotations


class BoundKernel:
    """A compiled kernel called through the machine-code entry point of the argument types of its
    first call, skipping numba's per-call type dispatch (~40 ns an argument and ~0.1 µs a call: ~3 µs
    of a safety step's ~100 arguments).

    Contract: every later call passes arguments of the first call's types (array dtype, ndim and
    layout; numba's entry point checks only that an array is one and its item size): the callers
    pass only buffers they own and inputs they have normalised. The first call (a pipeline's
    warm-up step) compiles the kernel or loads it from numba's disk cache; where numba has no
    such entry point the dispatcher itself is called (the same values, with its dispatch)."""

    __slots__ = ("dispatcher", "call")

    def __init__(self, dispatcher) -> None:
        self.dispatcher = dispatcher
        self.call = self._bind

    def _bind(self, *args):
        """The first call: bind :attr:`call` to the entry point of ``args``' types, then call it."""
        dispatcher = self.dispatcher
        try:
            self.call = dispatcher.compile(tuple(dispatcher.typeof_pyval(a) for a in args))
        except AttributeError:  # a numba without these: its dispatcher
            self.call = dispatcher
        return self.call(*args)
