"""The real and imaginary memories: capacity, first-in-first-out order, sampling, state."""

import pytest
import torch

from imagine.learning.memory import ReplayMemory, imaginary_fields, real_fields


def transitions(start, n, dim=2):
    ids = torch.arange(start, start + n, dtype=torch.float32)
    return {
        "z": ids[:, None].repeat(1, dim), "action": torch.arange(start, start + n) % 6,
        "next_z": ids[:, None].repeat(1, dim) + 0.5, "reward": ids, "done": torch.zeros(n),
    }  # fmt: skip


def test_capacity_and_first_in_first_out():
    memory = ReplayMemory(6, imaginary_fields(2))
    memory.add(**transitions(0, 4))
    assert len(memory) == 4
    memory.add(**transitions(4, 5))  # 9 added into 6 places: 0, 1, 2 are gone
    assert len(memory) == 6 and memory.added == [9]
    assert memory.newest(6)["reward"].tolist() == [3, 4, 5, 6, 7, 8]
    assert memory.newest(2)["reward"].tolist() == [7, 8]
    drawn = {k: v[0] for k, v in memory.sample(500, [torch.Generator().manual_seed(0)]).items()}
    assert set(drawn["reward"].tolist()) == {3.0, 4.0, 5.0, 6.0, 7.0, 8.0}
    # Fields stay aligned: each drawn transition is one stored transition.
    assert torch.equal(drawn["z"][:, 0], drawn["reward"])
    assert torch.equal(drawn["action"], drawn["reward"].long() % 6)


def test_a_batch_larger_than_the_memory_keeps_the_newest():
    memory = ReplayMemory(3, imaginary_fields(2))
    memory.add(**transitions(0, 10))
    assert memory.newest(3)["reward"].tolist() == [7, 8, 9]


def test_sampling_is_seeded_and_shaped():
    memory = ReplayMemory(50, real_fields(8))
    n = 20
    memory.add(mu=torch.randn(n, 8), sigma=torch.rand(n, 8), action=torch.randint(6, (n,)),
               next_mu=torch.randn(n, 8), next_sigma=torch.rand(n, 8), reward=torch.randn(n),
               done=torch.zeros(n))  # fmt: skip
    a = memory.sample(64, [torch.Generator().manual_seed(1)])
    b = memory.sample(64, [torch.Generator().manual_seed(1)])
    assert all(torch.equal(a[k], b[k]) for k in a)
    assert a["mu"].shape == (1, 64, 8) and a["action"].dtype == torch.int64


def test_errors_and_state_round_trip():
    memory = ReplayMemory(5, imaginary_fields(2))
    with pytest.raises(ValueError, match="empty"):
        memory.sample(1, [torch.Generator()])
    with pytest.raises(ValueError, match="expected fields"):
        memory.add(z=torch.zeros(1, 2))
    memory.add(**transitions(0, 7))
    copy = ReplayMemory(5, imaginary_fields(2))
    copy.load_state_dict(memory.state_dict("imaginary"), "imaginary")
    assert copy.newest(5)["reward"].tolist() == memory.newest(5)["reward"].tolist()
    copy.add(**transitions(7, 1))
    memory.add(**transitions(7, 1))
    assert copy.newest(5)["reward"].tolist() == [3, 4, 5, 6, 7]


def test_each_agent_has_its_own_ring_and_draws_with_its_own_generator():
    memory = ReplayMemory(4, imaginary_fields(2), agents=3)
    memory.add(0, **transitions(0, 6))  # agent 0 wraps around
    memory.add(2, **transitions(100, 2))
    memory.add_each([1, 2], **{k: v[:2] for k, v in transitions(50, 2).items()})
    assert memory.size == [4, 1, 3] and memory.added == [6, 1, 3]
    assert memory.newest(4, agent=0)["reward"].tolist() == [2, 3, 4, 5]
    assert memory.newest(3, agent=2)["reward"].tolist() == [100, 101, 51]
    drawn = memory.sample(200, [torch.Generator().manual_seed(0), None,
                                torch.Generator().manual_seed(0)])  # fmt: skip
    assert set(drawn["reward"][0].tolist()) == {2.0, 3.0, 4.0, 5.0}
    assert set(drawn["reward"][2].tolist()) == {100.0, 101.0, 51.0}
    # agent 2's draws depend only on its generator, not on the others
    alone = ReplayMemory(4, imaginary_fields(2))
    alone.load_state_dict(memory.state_dict("m", agent=2), "m")
    again = alone.sample(200, [torch.Generator().manual_seed(0)])
    assert torch.equal(again["reward"][0], drawn["reward"][2])
