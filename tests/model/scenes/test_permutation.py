"""The evaluated permutation behind the memory-flat ray sampler."""

import pytest
import torch

from model.scenes.permutation import FeistelPermutation


@pytest.mark.parametrize("n", [1, 2, 3, 5, 1000, 12_345, 2**16, 2**20 + 7])
def test_every_id_appears_exactly_once(n):
    out = FeistelPermutation(n, seed=3)(torch.arange(n))
    assert torch.equal(out.sort().values, torch.arange(n))


def test_a_slice_is_the_same_as_the_slice_of_the_whole_and_seeds_differ():
    n = 50_000
    perm = FeistelPermutation(n, seed=11)
    whole = perm(torch.arange(n))
    assert torch.equal(perm(torch.arange(12_000, 12_512)), whole[12_000:12_512])
    assert torch.equal(FeistelPermutation(n, seed=11)(torch.arange(n)), whole)  # deterministic
    other = FeistelPermutation(n, seed=12)(torch.arange(n))
    assert (other == whole).float().mean() < 0.01  # about 1/n agree by chance


def test_the_order_looks_random():
    n = 100_000
    out = FeistelPermutation(n, seed=0)(torch.arange(n)).double()
    position = torch.arange(n, dtype=torch.float64)
    # no trend between position and id, nor between neighbours
    assert abs(torch.corrcoef(torch.stack([position, out]))[0, 1]) < 0.02
    assert abs(torch.corrcoef(torch.stack([out[:-1], out[1:]]))[0, 1]) < 0.02
    # the first batch of an epoch spreads over the whole id range (chi-square over 20 bins, 19 dof)
    counts = torch.histc(out[:4096], bins=20, min=0, max=n)
    expected = 4096 / 20
    chi2 = float(((counts - expected) ** 2 / expected).sum())
    assert chi2 < 43.8  # p = 0.001
    # neighbouring ids (pixels of one image row) land far apart in the order
    inverse = torch.empty(n, dtype=torch.long)
    inverse[out.long()] = torch.arange(n)
    gaps = (inverse[1:] - inverse[:-1]).abs().double()
    assert float(gaps.median()) > 0.2 * n


def test_a_paper_sized_scene_costs_memory_in_the_batch_only():
    n = 1_900_000_000  # Mega-NeRF Building at 1/4 scale: 15 GB as a randperm
    perm = FeistelPermutation(n, seed=5)
    batch = perm(torch.arange(n - 8192, n))
    assert batch.dtype == torch.int64 and len(batch.unique()) == 8192
    assert int(batch.min()) >= 0 and int(batch.max()) < n


def test_bad_arguments_are_named():
    with pytest.raises(ValueError, match="at least one element"):
        FeistelPermutation(0, seed=0)
    with pytest.raises(ValueError, match=r"out of \[0, 10\)"):
        FeistelPermutation(10, seed=0)(torch.tensor([10]))
