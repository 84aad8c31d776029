"""A training selection: the kept episodes of a set of explore shards, and its digest."""

from __future__ import annotations

from dataclasses import dataclass

import pyarrow as pa

from schemas.keys import digest_of
from warehouse.catalog import Catalog
from warehouse.training_reader import RowRange, select_rows


_KEPT = "SELECT episode_id FROM filter_decisions WHERE kept AND list_contains(?, filter_key)"


def _narrowed(where: str | None) -> str:
    kept = f"episode_id IN ({_KEPT})"
    return kept if where is None else f"{kept} AND ({where})"


@dataclass(frozen=True)
class Selection:
    explore_units: tuple[str, ...]
    filter_units: tuple[str, ...]

    def _params(self) -> list:
        return [list(self.explore_units), list(self.filter_units)]

    def rows(self, catalog: Catalog, where: str | None = None) -> list[RowRange]:
        """The kept steps (those also matching `where`, SQL over the steps columns), as the
        streaming reader takes them."""
        return select_rows(catalog, _narrowed(where), [list(self.filter_units)], units=list(self.explore_units))

    def kept_steps(self, catalog: Catalog, columns: list[str], where: str | None = None) -> pa.Table:
        """Columns of the kept steps (matching `where`), in a fixed order: a parallel scan returns
        rows in varying order, and float sums in another order differ in the last bits."""
        return catalog.query_arrow(
            f"SELECT {', '.join(columns)} FROM steps WHERE {_narrowed(where)} ORDER BY episode_id, step",
            [list(self.filter_units)], confined=True,
        )

    def digest(self, catalog: Catalog) -> str:
        """Digest of the exact shard files read: same digest, same training data."""
        rows = catalog.query(
            "SELECT sha256 FROM shards WHERE (table_name = 'steps' AND list_contains(?, unit_key)) "
            "OR (table_name = 'filter_decisions' AND list_contains(?, unit_key))",
            self._params(),
        )
        return digest_of([row[0] for row in rows])

    def counts(self, catalog: Catalog) -> dict[str, int]:
        [(episodes, kept, triplets)] = catalog.query(
            """
            WITH kept AS (SELECT episode_id FROM filter_decisions WHERE kept AND list_contains($2, filter_key))
            -- the same selection as _KEPT, with the filter units as the second parameter
            SELECT (SELECT count(*) FROM episodes WHERE list_contains($1, shard_key)),
                   (SELECT count(*) FROM kept),
                   (SELECT count(*) FROM steps WHERE episode_id IN (SELECT episode_id FROM kept))
            """,
            self._params(),
        )
        return {"episodes": episodes, "kept_episodes": kept, "triplets": triplets}
