"""Reversible attribute patches (the model's own code is never edited; state lives outside it).

Like diffusers' ``HookRegistry``: an instance attribute shadows the class method, so removing it
restores the model exactly; one accelerator at a time may own a module.
"""
from __future__ import annotations

import functools
import weakref
from typing import Any, Callable

__all__ = ["Patches"]

_OWNED: "weakref.WeakKeyDictionary[Any, object]" = weakref.WeakKeyDictionary()
_MISSING = object()


class Patches:
    """A stack of ``obj.name = wrapper(original)`` patches, undone in reverse order."""

    def __init__(self, owner: object):
        self._owner = owner
        self._items: list[tuple[Any, str, Any]] = []

    def patch(self, obj: Any, name: str, make: Callable[[Callable], Callable]) -> None:
        """Set ``obj.name = make(original)``; an error if another accelerator owns ``obj``."""
        holder = _OWNED.get(obj)
        if holder is not None and holder is not self._owner:
            raise RuntimeError(
                f"{type(obj).__name__} is already accelerated by another tts accelerator; "
                "call .remove() on it first"
            )
        original = getattr(obj, name)
        new = make(original)
        functools.update_wrapper(new, original)
        self._items.append((obj, name, obj.__dict__.get(name, _MISSING)))
        object.__setattr__(obj, name, new)
        _OWNED[obj] = self._owner

    def restore(self) -> None:
        """Undo every patch, newest first: each object is exactly as before."""
        for obj, name, saved in reversed(self._items):
            if saved is _MISSING:
                object.__delattr__(obj, name)
            else:
                object.__setattr__(obj, name, saved)
            _OWNED.pop(obj, None)
        self._items.clear()

    def __len__(self) -> int:
        return len(self._items)
