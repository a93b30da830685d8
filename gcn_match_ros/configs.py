"""Settings dataclasses that travel as JSON (inside checkpoints): one rule for to/from dicts."""
from __future__ import annotations

import dataclasses
from typing import Any, Dict, Type, TypeVar

__all__ = ["JsonConfig"]

C = TypeVar("C", bound="JsonConfig")


def _plain(value: Any) -> Any:
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    return value


class JsonConfig:
    """Mixin of a (frozen) settings dataclass: :meth:`to_dict` gives plain JSON values (tuples
    become lists, nested settings nested dicts), :meth:`from_dict` reads them back and refuses
    keys the class does not have."""

    def to_dict(self) -> Dict[str, Any]:
        return _plain(dataclasses.asdict(self))

    @classmethod
    def from_dict(cls: Type[C], d: Dict[str, Any]) -> C:
        """Inverse of :meth:`to_dict`.

        Raises:
            ValueError: a key that is not a field (named), or an invalid value.
        """
        fields = {f.name: f for f in dataclasses.fields(cls)}
        unknown = set(d) - set(fields)
        if unknown:
            raise ValueError(f"{cls.__name__}: unknown keys {sorted(unknown)}")
        values = dict(d)
        for name, value in d.items():
            nested = type(fields[name].default)
            if isinstance(value, dict) and issubclass(nested, JsonConfig):
                values[name] = nested.from_dict(value)
        return cls(**values)
