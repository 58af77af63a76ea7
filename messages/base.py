"""Base class of every message: a frozen msgspec struct that refuses non-finite floats."""

from __future__ import annotations

import math

import msgspec


class Message(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """A frozen, typed message.

    Range constraints declared with :class:`msgspec.Meta` are enforced when decoding (and so by
    :func:`messages.codec.encode`, which validates by round trip). Non-finite floats are refused
    on construction and on decoding, because JSON has no NaN/inf and an encoder would silently
    turn them into ``null``.
    """

    def __post_init__(self) -> None:
        for name in self.__struct_fields__:
            value = getattr(self, name)
            if isinstance(value, float) and not math.isfinite(value):
                raise ValueError(f"field `{name}` is not finite ({value})")
            if isinstance(value, (list, tuple)):
                for item in value:
                    if isinstance(item, float) and not math.isfinite(item):
                        raise ValueError(f"field `{name}` holds a non-finite value ({item})")
