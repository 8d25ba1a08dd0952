"""The zoo ablation's comparison: paired by bag, per class, the discordant bags named, the sign test exact."""

from bagit.bench import zoo_ablation


def _run(i: int, success: bool, reason: str | None = None, slowed: int = 0, commit: str = "abc1234") -> dict:
    return {"scenario": f"zoo-core-0-{i}", "success": success, "error_cm": 0.3 if success else 2.0, "duration_s": 10.0 + i,
            "stage_reached": "done" if success else "bagging", "reason": reason, "overrides": {},
            "arm_events": {"slowed": slowed}, "provenance": {"commit": commit, "dirty": False, "host": "vm", "date": f"2026-11-27T1{i}:00:00"}}


BAGS = {f"zoo-core-0-{i}": {"classes": ["soft"] if i % 2 else ["stiff"]} for i in range(6)}


def test_pairs_bags_names_the_discordant_ones_and_tests_them_exactly():
    online = [_run(i, True) for i in range(5)]
    frozen = [_run(0, True), _run(1, False, "time limit of 40 s reached in bagging", slowed=7), _run(2, False, "perception lost the rim"),
              _run(3, False, "time limit of 40 s reached in bagging"), _run(4, False, "time limit of 40 s reached in bagging"),
              _run(5, True)]
    r = zoo_ablation.compare(online, frozen, ("online", "frozen"), BAGS)
    assert r["bags"] == 5 and r["only_in"] == {"online": [], "frozen": ["zoo-core-0-5"]}
    assert r["summary"]["online"]["all"]["success"] == 5 and r["summary"]["frozen"]["all"]["success"] == 1
    assert r["summary"]["frozen"]["soft"] == {"success": 0, "of": 2, "rate": 0.0, "error_cm_mean": None, "time_s_mean": None}
    assert [x["bag"] for x in r["bagged_only_with"]["online"]] == [f"zoo-core-0-{i}" for i in (1, 2, 3, 4)]
    assert r["bagged_only_with"]["online"][0]["other"] == {"cause": "control", "stage": "bagging",
                                                           "reason": "time limit of 40 s reached in bagging", "slowed": 7}
    assert r["bagged_only_with"]["frozen"] == []
    assert r["causes"]["frozen"] == {"control": 3, "perception": 1}
    assert r["sign_test_p"] == 0.125  # 4 against 0: 2 * (1/2)**4
    md = zoo_ablation.markdown(r)
    assert "**Partial**: 1 bags only in the frozen record" in md and "| all | 5/5, 0.30, 12.0 | 1/5, 0.30, 10.0 |" in md
    assert "- zoo-core-0-1 (soft): control: bagging: time limit of 40 s reached in bagging (arms slowed 7 periods)" in md


def test_no_discordant_bag_gives_p_one_and_a_resumed_record_counts_its_last_line():
    a = [_run(0, False, "x"), _run(0, True)]
    r = zoo_ablation.compare(a, [_run(0, True)], ("a", "b"), BAGS)
    assert r["bags"] == 1 and r["sign_test_p"] == 1.0 and "Partial" not in zoo_ablation.markdown(r)
