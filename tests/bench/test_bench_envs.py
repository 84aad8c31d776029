"""`sim2act bench envs` runs every family's layers in real simulators and writes its table."""

from bench.envs import COLLIDING_FAMILIES, LAYERS, MESH_DETAIL_FAMILIES, STOCK_CONTROL_LAYERS
from flows.cli import main
from schemas.tasks import FAMILIES


def test_bench_envs_reports_every_layer_per_family_against_the_raw_step(tmp_path, capsys):
    out = tmp_path / "docs" / "bench-envs.md"
    assert main(["bench", "envs", "--steps", "20", "--out", str(out)]) == 0
    table = out.read_text()
    assert "`sim2act bench envs --steps 20 --out" in table
    lines = [line.split(" | ") for line in table.splitlines() if line.startswith("| ") and "---" not in line]
    rows = [line for line in lines if len(line) == 5][1:]  # the layers' table; then the render shares'
    shares = {line[0].strip("| "): line[1:] for line in lines if len(line) == 4}
    by_family: dict[str, dict[str, tuple[float, float]]] = {}
    for family, _, layer, rate, ratio in rows:
        by_family.setdefault(family.strip("| "), {})[layer] = (float(rate.replace(",", "")), float(ratio.strip(" |")))
    assert set(by_family) == set(FAMILIES)
    for family, layers in by_family.items():
        expected = set(LAYERS) - ({"simulator env.step"} if family == "navigation" else set())
        expected -= set() if family in MESH_DETAIL_FAMILIES else {LAYERS[4]}
        expected -= set() if family in COLLIDING_FAMILIES else {LAYERS[5]}
        expected |= set(STOCK_CONTROL_LAYERS) if family == "robosuite" else set()
        assert set(layers) == expected, family
        assert layers["raw mj_step"][1] == 1.0
        assert all(rate > 0 for rate, _ in layers.values())
        # a frame costs more than the physics under it, in every family
        assert layers["sim2act adapter + 84px render"][0] < layers["sim2act adapter"][0] < layers["raw mj_step"][0]
    # the render's share of an adapter step, per family; decimated meshes only where the adapter has them
    assert set(shares) == set(FAMILIES) | {"family"}
    for family in FAMILIES:
        full, coarse, coarser = (cell.strip("| ") for cell in shares[family])
        assert full.endswith("%") and (coarse.endswith("%") if family in MESH_DETAIL_FAMILIES else coarse == "—")
        assert coarser.endswith("%") if family in COLLIDING_FAMILIES else coarser == "—"
    assert "navigation" in capsys.readouterr().out


def test_bench_envs_refuses_bad_input_before_any_work(capsys):
    assert main(["bench", "envs", "--steps", "0"]) == 2
    assert "--steps must be at least 1" in capsys.readouterr().err
