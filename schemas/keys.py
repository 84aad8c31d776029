"""Unit keys and seeds: the stage contract's hashes (docs/architecture.md)."""

from __future__ import annotations

import hashlib
import json
from collections.abc import Mapping, Sequence
from typing import Any

from pydantic import BaseModel


def _canonical(value: Any) -> Any:
    if isinstance(value, BaseModel):
        return value.model_dump(mode="json")
    raise TypeError(f"{type(value).__name__} cannot be part of a unit key")


def unit_key(stage: str, version: int, config: Mapping[str, Any] | BaseModel, inputs: Sequence[str] = ()) -> str:
    """Key of one unit of work: hash of (stage, stage version, the config it reads, its input keys).

    Two runs that would compute the same output get the same key, so a registered key means
    the work is done.
    """
    payload = json.dumps(
        {"stage": stage, "version": version, "config": config, "inputs": list(inputs)},
        default=_canonical,
        sort_keys=True,
        separators=(",", ":"),
    )
    return f"{stage}-{hashlib.blake2b(payload.encode(), digest_size=8).hexdigest()}"


def key_fields(config: BaseModel, exclude: set[str], legacy: Mapping[str, Any]) -> dict[str, Any]:
    """A config as a unit key reads it: without `exclude` (how a stage runs, not what it makes), and
    without each field added after the stage's version that holds its `legacy` value (the one that
    does what the stage did before the field existed), so work done before it keeps its key. A nested
    model's added fields are a mapping under its name."""
    return _without_legacy(config.model_dump(exclude=exclude), legacy)


def _without_legacy(fields: dict[str, Any], legacy: Mapping[str, Any]) -> dict[str, Any]:
    kept = {}
    for name, value in fields.items():
        old = legacy.get(name, _ABSENT)
        if isinstance(old, Mapping) and isinstance(value, dict):
            kept[name] = _without_legacy(value, old)
        elif old is _ABSENT or value != old:
            kept[name] = value
    return kept


_ABSENT = object()


def derive_seed(*parts: object) -> int:
    """A 31-bit seed from (campaign, iteration, task, shard, episode, ...): re-runs reproduce data."""
    digest = hashlib.blake2b("/".join(map(str, parts)).encode(), digest_size=8).digest()
    return int.from_bytes(digest, "little") % (2**31 - 1)


def digest_of(items: Sequence[str]) -> str:
    """Order-independent digest of a set of keys (e.g. the shard digests a training run read)."""
    return hashlib.blake2b("\n".join(sorted(items)).encode(), digest_size=16).hexdigest()
