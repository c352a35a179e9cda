"""numba disk caches that go stale when a module they compile in changes: key them on its source.

numba's `cache=True` checks only the file of the function it compiles. A kernel in another
module that calls `onboard.model` functions compiles them into itself, so after an edit of
onboard/model.py a plainly cached kernel would go on running the old physics (reproduced).
`key_caches_on(namespace, *sources)` re-keys every cached kernel defined in a module on the
hashes of `sources` too. If numba's caching internals move, a kernel is simply not cached
(compiled once per process), never stale.
"""

from __future__ import annotations

import hashlib
from pathlib import Path

MODEL_SOURCE = Path(__file__).with_name("model.py")


def cache_keyed_on(dispatcher, *sources: Path) -> None:
    """Cache `dispatcher` on disk, invalid once its own file or any of `sources` changes."""
    try:
        from numba.core.caching import CompileResultCacheImpl, FunctionCache

        digests = tuple(hashlib.sha256(Path(f).read_bytes()).hexdigest() for f in sources)

        class _Stamped:
            def __init__(self, inner):
                self._inner = inner

            def __getattr__(self, name):
                return getattr(self._inner, name)

            def get_source_stamp(self):
                return (self._inner.get_source_stamp(), digests)

        class _Impl(CompileResultCacheImpl):
            def __init__(self, py_func):
                super().__init__(py_func)
                self._locator = _Stamped(self._locator)

        class _Cache(FunctionCache):
            _impl_class = _Impl

        dispatcher._cache = _Cache(dispatcher.py_func)
    except Exception:  # pragma: no cover - a numba without these internals, or no writable cache dir
        pass


def key_caches_on(namespace: dict, *sources: Path) -> None:
    """Re-key every disk-cached numba kernel defined in the module `namespace` on `sources`."""
    from numba.core.caching import FunctionCache
    from numba.core.registry import CPUDispatcher

    for obj in list(namespace.values()):
        if (isinstance(obj, CPUDispatcher) and obj.py_func.__module__ == namespace["__name__"]
                and isinstance(getattr(obj, "_cache", None), FunctionCache)):
            cache_keyed_on(obj, *sources)
