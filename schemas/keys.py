"""Unit keys and seeds: the stage contract's hashes (see ARCHITECTURE.md)."""

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
    does what the stage did before the field existed), so work done before it keeps its key."""
    fields = config.model_dump(exclude=exclude)
    return {k: v for k, v in fields.items() if k not in legacy or v != legacy[k]}


def derive_seed(*parts: object) -> int:
    """A 31-bit seed from (campaign, iteration, task, shard, episode, ...): re-runs reproduce data."""
    digest = hashlib.blake2b("/".join(map(str, parts)).encode(), digest_size=8).digest()
    return int.from_bytes(digest, "little") % (2**31 - 1)


def digest_of(items: Sequence[str]) -> str:
    """Order-independent digest of a set of keys (e.g. the shard digests a training run read)."""
    return hashlib.blake2b("\n".join(sorted(items)).encode(), digest_size=16).hexdigest()
