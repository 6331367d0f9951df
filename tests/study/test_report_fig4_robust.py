"""Figure 4's verdicts and their realisations (docs/report.md; issue 56): two results folders of
the protocol whose verdicts differ make each verdict ``not robust``; one folder of fewer than 10
repetitions keeps its verdict with the shortfall said; other claims are untouched."""

from __future__ import annotations

from types import SimpleNamespace

from taskvar_torch.study.report_claims import NOT_ROBUST, Claim, fig4_robustness


def _group(
    label: str, reps: int, kind: str = "wargus-fig4", protocol: str = "fig4"
) -> SimpleNamespace:
    return SimpleNamespace(label=label, kind=kind, seeds=list(range(reps)), protocol=protocol)


def _claim(key: str, group: str, verdict: str) -> Claim:
    return Claim(key, group, "ours", verdict, "why")


def test_realisations_that_disagree_are_not_robust():
    groups = [
        _group("fig4 a", 5),
        _group("fig4 b", 5),
        _group("fig4 16x16", 5, protocol="16x16"),  # another protocol: not a realisation
        _group("windy", 5, "windy-fig2"),
    ]
    claims = [
        _claim("fig4_order", "fig4 a", "partly"),
        _claim("fig4_order", "fig4 b", "not"),
        _claim("fig4_speed", "fig4 a", "not"),
        _claim("fig4_speed", "fig4 b", "not"),
        _claim("fig4_order", "fig4 16x16", "reproduced"),
        _claim("fig2", "windy", "reproduced"),
    ]
    out = fig4_robustness(claims, groups)
    verdicts = [c.verdict for c in out]
    assert verdicts == [NOT_ROBUST, NOT_ROBUST, "not", "not", "reproduced", "reproduced"]
    assert "realisations disagree: partly (fig4 a); not (fig4 b)" in out[0].reason
    assert out[2].reason == "why" and out[5] is claims[5]  # agreeing realisations: as they were


def test_one_realisation_needs_ten_repetitions_to_stand_alone():
    few = fig4_robustness([_claim("fig4_order", "a", "partly")], [_group("a", 5)])[0]
    assert few.verdict == "partly" and "one realisation of 5 repetitions (< 10)" in few.reason
    ten = fig4_robustness([_claim("fig4_order", "a", "partly")], [_group("a", 10)])[0]
    assert ten.verdict == "partly" and ten.reason == "why"
