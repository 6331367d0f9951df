"""The oracle-table job: exact per-start returns, a JSON table and a grid PNG."""

from __future__ import annotations

import json

import torch

from taskvar_torch.families.windy import oracle_table

torch.set_num_threads(1)


def test_oracle_table_writes_json_and_png(tmp_path, capsys):
    result = oracle_table.main(["--out", str(tmp_path)])
    out = capsys.readouterr().out
    assert "uniform start" in out and "(2, 0)" in out
    saved = json.loads((tmp_path / "oracle_table.json").read_text())
    assert [tuple(r["start"]) for r in saved["rows"]] == [(r, 0) for r in range(5)]
    rows = {tuple(r["start"]): r for r in result["rows"]}
    # the default layout is north/south symmetric; the centre start is the farthest from an exit
    assert abs(rows[(0, 0)]["averaging_train"] - rows[(4, 0)]["averaging_train"]) < 1e-9
    assert (
        rows[(2, 0)]["averaging_train"]
        < rows[(1, 0)]["averaging_train"]
        < rows[(0, 0)]["averaging_train"]
    )
    png = (tmp_path / "grid.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 5000
