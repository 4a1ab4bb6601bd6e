"""benchmarks/launch_choice.py: the launch-estimate variant chosen by the rule declared before the calibration call."""

import importlib.util
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
spec = importlib.util.spec_from_file_location("launch_choice", ROOT / "benchmarks/launch_choice.py")
launch_choice = importlib.util.module_from_spec(spec)
spec.loader.exec_module(launch_choice)


def _row(variant: str, seed: int, along: float, plane: float) -> str:
    return f"{variant:50s} seed {seed} {+0.14:+8.2f} {along:+9.2f} {plane:8.2f} {1.0:7.2f} {0.1:8.4f}"


def test_the_rule_reads_the_rows_and_prefers_the_earlier_variant_within_the_tie(tmp_path):
    """Rows printed as each fit ends (a header, a repeated row, tqdm noise between) are read once each; the lowest
    median |v0 error| wins unless an earlier variant is within 0.05 m/s; a variant not fitted on every unit is out."""
    lines = {"calib_torus_seed0": [_row("params.yaml", 0, -2.0, 0.1), _row("a=1", 0, -0.30, 0.0),
                                   _row("b=1", 0, -0.27, 0.0), _row("c=1", 0, -0.01, 0.0)],
             "calib_star_seed1": [_row("params.yaml", 1, -1.0, 0.0), _row("a=1", 1, -0.40, 0.0),
                                  _row("b=1", 1, -0.37, 0.0), "velocity: 100%|####| 100/100",
                                  _row("b=1", 1, -0.37, 0.0)]}
    for name, rows in lines.items():
        (tmp_path / f"{name}.log").write_text("variant  seed  gt along\n" + "\n".join(rows) + "\n")
    table = launch_choice.rows(tmp_path)
    assert len(table) == 7 and {r["scene"] for r in table} == {"calib_torus", "calib_star"}
    result = launch_choice.main([str(tmp_path)])
    medians = {v["variant"]: v["median_error"] for v in result["variants"]}
    assert abs(medians["params.yaml"] - (2.0025 + 1.0) / 2) < 1e-3 and abs(medians["b=1"] - 0.32) < 1e-9
    assert result["choice"] == "a=1"  # b=1 is 0.03 m/s lower: within the tie, the earlier stays; c=1 has one unit
    assert (tmp_path / "launch_choice.json").is_file()
