"""The restart budget as a rate (issue 38.8): a token bucket on a fake clock."""

import pytest

from pipeline.stream.budget import RestartBudget
from pipeline.stream.topology import load_topology


class Clock:
    def __init__(self):
        self.t = 1000.0

    def __call__(self):
        return self.t


def test_a_burst_spends_the_budget_and_the_same_deaths_spread_out_do_not():
    clock = Clock()
    burst = RestartBudget(10, 60.0, clock)
    taken = [burst.take() for _ in range(11)]  # 11 deaths within a second
    assert taken == [True] * 10 + [False]

    clock2 = Clock()
    spread = RestartBudget(10, 60.0, clock2)
    for _ in range(11):  # the same 11 deaths, one every 30 s: half a restart back each time
        assert spread.take()
        clock2.t += 30.0
    # a week of one death a minute (the soak's source died every ~60 s at its worst)
    for _ in range(7 * 24 * 60):
        clock2.t += 60.0
        assert spread.take()
    assert spread.available() >= 4.0


def test_the_budget_refills_at_its_rate_and_never_past_its_burst():
    clock = Clock()
    b = RestartBudget(3, 10.0, clock)
    assert [b.take() for _ in range(4)] == [True, True, True, False]
    assert b.spent() == 3
    clock.t += 9.9
    assert not b.take()  # 0.99 earned: not a whole restart
    clock.t += 0.2
    assert b.take() and b.spent() == 3
    clock.t += 10_000.0
    assert b.available() == 3.0 and b.spent() == 0


def test_a_zero_budget_fails_the_first_death():
    assert not RestartBudget(0, 60.0, Clock()).take()
    with pytest.raises(ValueError):
        RestartBudget(1, 0.0, Clock())


@pytest.mark.parametrize("daemon, refill", [("", 60.0), ("restart_refill_s = 5\n", 5.0),
                                            ("restart_window_s = 300\n", 30.0)])
def test_the_topology_sets_the_rate(tmp_path, daemon, refill):
    """`restart_refill_s` (default 60 s); a topology from before, with restart_window_s,
    keeps its long-run rate: window / restarts."""
    (tmp_path / "t.toml").write_text(
        f'[daemon]\nstate = "{tmp_path / "s"}"\nrestarts = 10\n{daemon}'
        f'[source]\nkind = "udp"\nbind = "127.0.0.1:9"\nn_tdc = 8\n'
        f'[histogram]\nartifacts = "count-as-hits"\n[sink]\nout = "{tmp_path / "o"}"\n')
    assert load_topology(tmp_path / "t.toml").restart_refill_s == refill
