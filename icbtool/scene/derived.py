"""Data derived from a :class:`~icbtool.scene.Scene`, kept outside it.

A Scene is immutable, so anything computed from it (an Embree BVH, the tracer's kernel arrays,
content hashes, face normals) stays valid for the scene's lifetime. Those values live here, keyed
by the scene object (weakly: they go when the scene goes), never in the Scene itself, so no
package writes into another's object. A changed scene is a new object (``dataclasses.replace``)
and starts with nothing cached.

Example:
    >>> from icbtool.scene.derived import derived
    >>> # bvh = derived(scene, "embree_robust=True", lambda: build_bvh(scene))
"""

from __future__ import annotations

import threading
import weakref
from collections.abc import Callable
from typing import Any, TypeVar

T = TypeVar("T")

_STORE: weakref.WeakKeyDictionary[Any, dict[str, Any]] = weakref.WeakKeyDictionary()
_LOCK = threading.RLock()


def derived(scene: Any, key: str, build: Callable[[], T]) -> T:
    """The value cached for ``(scene, key)``; ``build()`` computes it on first use.

    Args:
        scene: the (immutable) scene the value is derived from.
        key: what the value is, including every parameter it depends on (e.g.
            ``"embree_robust=True"``).
        build: computes the value from the scene.

    Returns:
        The cached value (the same object on every call for this scene and key).
    """
    with _LOCK:
        values = _STORE.get(scene)
        if values is None:
            values = _STORE[scene] = {}
        if key in values:
            return values[key]
    value = build()  # outside the lock: builds may be slow (a BVH) and may call derived()
    with _LOCK:
        return values.setdefault(key, value)


def cached_keys(scene: Any) -> tuple[str, ...]:
    """The keys of what is cached for ``scene`` (for tests and diagnostics)."""
    with _LOCK:
        return tuple(_STORE.get(scene, {}))


def forget(scene: Any) -> None:
    """Drop everything cached for ``scene`` (frees memory early; never needed for correctness)."""
    with _LOCK:
        _STORE.pop(scene, None)


__all__ = ["cached_keys", "derived", "forget"]
