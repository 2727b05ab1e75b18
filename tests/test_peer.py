"""The peer baseline row of `imagine reproduce --baselines sb3` (issue 16): SB3's DQN on
GesturePuzzle, judged on our test episodes, as a column of Tables I and II."""

import pytest

from imagine.errors import ConfigError
from imagine.study import peer
from imagine.study.report import markdown_table, summarize
from imagine.study.reproduce import StudyConfig, same_study


def evaluation(method, seed, budget, success):
    return {"task": "hard", "method": method, "seed": seed, "budget": budget, "success": success}


def test_the_peer_is_a_column_only_where_a_study_has_it():
    ours = [evaluation(m, s, 2000, 0.5 + 0.1 * s) for m in ("baseline", "augmented")
            for s in range(3)]  # fmt: skip
    plain = markdown_table("hard", summarize(ours), 0.03)
    assert "SB3" not in plain
    peers = [evaluation("sb3-dqn", s, 2000, 0.1 * s) for s in range(3)]
    rows = summarize(ours + peers)
    table = markdown_table("hard", rows, 0.03)
    header, rule, line, random = table.splitlines()
    assert "| SB3 DQN | IQM SB3 DQN [95% CI] |" in header
    assert header.count("|") == rule.count("|") == line.count("|") == random.count("|")
    assert line.endswith("| 10.00 (10.00) | 10.00 [0.00, 20.00] |")  # mean (std) of 0, 10, 20
    sb3 = [r for r in rows if r["method"] == "sb3-dqn"]
    assert len(sb3) == 1 and sb3[0]["paper_mean"] != sb3[0]["paper_mean"]  # no paper number


def test_baselines_are_checked_and_do_not_change_the_study():
    with pytest.raises(ConfigError, match="unknown baseline 'ppo'"):
        StudyConfig(preset="smoke", baselines=("ppo",))
    plain = StudyConfig(preset="smoke", tasks=("hard",))
    saved = {k: (list(v) if isinstance(v, tuple) else v) for k, v in vars(plain).items()}
    assert same_study(saved, StudyConfig(preset="smoke", tasks=("hard",), baselines=("sb3",)))


def test_without_sb3_the_row_is_skipped_in_one_line(tmp_path, monkeypatch):
    monkeypatch.setattr(peer, "sb3_available", lambda: False)
    lines = []
    peer.run_peers(("sb3",), tmp_path, ("hard",), (0,), (10,), 20, 0, log=lines.append)
    assert len(lines) == 1 and "pip install 'imagine[sb3]'" in lines[0]
    assert not (tmp_path / "sb3-dqn").exists()


@pytest.mark.skipif(not peer.sb3_available(), reason="Stable-Baselines3 is not installed")
def test_sb3_learns_on_gesture_puzzle_and_is_judged_on_our_test_episodes(tmp_path):
    """SB3's DQN trains by episodes, is evaluated as its episode count passes each budget, in
    our evaluations' format; a finished budget is not run again."""
    folder = peer.peer_folder(tmp_path, "hard", 0)
    peer.train_peer("hard", 0, (5, 10), folder, 30, 7, log=lambda m: None)
    found = peer.peer_evaluations(tmp_path, ("hard",), (0, 1), (5, 10))
    assert [(e["method"], e["budget"], e["episodes"]) for e in found] == [
        ("sb3-dqn", 5, 30), ("sb3-dqn", 10, 30)]  # fmt: skip
    assert all(0 <= e["success"] <= 1 and e["time_steps"] >= e["budget"] for e in found)
    lines = []
    peer.run_peers(("sb3",), tmp_path, ("hard",), (0,), (5, 10), 30, 7, log=lines.append)
    assert lines == []  # nothing left to run


def test_agents_acting_on_a_belief_show_their_success_on_v_means_too():
    ours = [evaluation(m, s, 2000, 0.5 + 0.1 * s) for m in ("baseline", "augmented")
            for s in range(3)]  # fmt: skip
    assert "V's means" not in markdown_table("hard", summarize(ours), 0.03)
    for e in ours:
        if e["method"] == "augmented":
            e["success_observation"] = e["success"] - 0.1
    rows = summarize(ours)
    assert [r["observation_mean"] for r in rows if r["method"] == "augmented"] == [
        pytest.approx(50.0)
    ]
    header, rule, line, random = markdown_table("hard", rows, 0.03).splitlines()
    assert "| Augmented on V's means |" in header
    assert header.count("|") == rule.count("|") == line.count("|") == random.count("|")
    assert line.startswith("| 2000 | 60.00 (10.00) | 60.00 (10.00) |")
    assert line.endswith("| 50.00 (10.00) |")
    peers = [evaluation("sb3-dqn", s, 2000, 0.1 * s) for s in range(3)]
    header, _, line, _ = markdown_table("hard", summarize(ours + peers), 0.03).splitlines()
    assert header.endswith("| Augmented on V's means | SB3 DQN | IQM SB3 DQN [95% CI] |")
    assert line.endswith("| 50.00 (10.00) | 10.00 (10.00) | 10.00 [0.00, 20.00] |")
