"""The hash encoding (model/fields/hash_encoding.py) against references: a dense grid read by
torch's own trilinear interpolation where no level collides, and a per-point loop over the paper's
hash where levels do; and the scene contraction's continuity and bounds."""

import math

import pytest
import torch
import torch.nn.functional as F

from model.fields.contraction import contract, contracted_unit
from model.fields.hash_encoding import PRIMES, HashEncoding
from model.sizes import level_resolutions


def dense_reference(encoding: HashEncoding, x: torch.Tensor) -> torch.Tensor:
    """Each level's table read as a dense (N+1)^3 volume by grid_sample (align_corners: -1 and 1 are
    the first and last corners)."""
    out = []
    for level, n in enumerate(encoding.resolutions):
        start = int(encoding.offsets[level])
        table = encoding.table[start : start + (n + 1) ** 3]
        volume = table.reshape(n + 1, n + 1, n + 1, -1).permute(3, 0, 1, 2)[None]  # (1, F, z, y, x)
        grid = (x * 2 - 1).view(1, 1, 1, -1, 3)
        sampled = F.grid_sample(volume, grid, mode="bilinear", align_corners=True)
        out.append(sampled.view(encoding.features, -1).T)
    return torch.cat(out, dim=-1)


def loop_reference(encoding: HashEncoding, x: torch.Tensor) -> torch.Tensor:
    """One point, one level, one corner at a time, straight from the paper's Eq. 4."""
    rows = []
    for point in x.tolist():
        features = []
        for level, n in enumerate(encoding.resolutions):
            scaled = [c * n for c in point]
            low = [min(math.floor(s), n - 1) for s in scaled]
            blended = torch.zeros(encoding.features, dtype=encoding.table.dtype)
            for corner in range(8):
                offset = [(corner >> axis) & 1 for axis in range(3)]
                i, j, k = (low[a] + offset[a] for a in range(3))
                if (n + 1) ** 3 > encoding.table_size:
                    index = (i * PRIMES[0] ^ j * PRIMES[1] ^ k * PRIMES[2]) % encoding.table_size
                else:
                    index = i + j * (n + 1) + k * (n + 1) ** 2
                weight = 1.0
                for a in range(3):
                    frac = scaled[a] - low[a]
                    weight *= frac if offset[a] else 1 - frac
                blended = blended + weight * encoding.table[int(encoding.offsets[level]) + index]
            features.append(blended)
        rows.append(torch.cat(features))
    return torch.stack(rows)


def test_the_levels_grow_geometrically_from_the_coarsest_to_the_finest():
    assert level_resolutions(16, 16, 2048)[0] == 16 and level_resolutions(16, 16, 2048)[-1] == 2048
    resolutions = level_resolutions(4, 2, 16)
    assert resolutions == [2, 4, 8, 16]


def test_values_and_gradients_match_a_dense_grid_where_no_level_collides():
    torch.manual_seed(0)
    encoding = HashEncoding(
        levels=3, features=2, log2_table_size=12, min_resolution=2, max_resolution=8
    ).double()
    assert not encoding.hashed.any()  # 9^3 = 729 corners fit in 4,096 entries
    with torch.no_grad():
        encoding.table.normal_()
    x = torch.rand(64, 3, dtype=torch.float64)
    x[0] = torch.tensor([1.0, 1.0, 1.0])  # the far corner of the box uses the last cell
    x[1] = torch.tensor([0.0, 0.5, 1.0])
    ours, reference = encoding(x), dense_reference(encoding, x)
    assert torch.allclose(ours, reference, atol=1e-12)
    weights = torch.randn_like(ours)
    (grad_ours,) = torch.autograd.grad((ours * weights).sum(), encoding.table)
    (grad_ref,) = torch.autograd.grad(
        (dense_reference(encoding, x) * weights).sum(), encoding.table
    )
    assert torch.allclose(grad_ours, grad_ref, atol=1e-12)


def test_values_and_gradients_match_the_papers_hash_where_levels_collide():
    torch.manual_seed(1)
    encoding = HashEncoding(
        levels=4, features=2, log2_table_size=6, min_resolution=2, max_resolution=32
    ).double()
    assert encoding.hashed.tolist() == [False, True, True, True]  # 27 corners fit in 64; 125 do not
    with torch.no_grad():
        encoding.table.normal_()
    x = torch.rand(24, 3, dtype=torch.float64)
    ours, reference = encoding(x), loop_reference(encoding, x)
    assert torch.allclose(ours, reference, atol=1e-12)
    weights = torch.randn_like(ours)
    (grad_ours,) = torch.autograd.grad((ours * weights).sum(), encoding.table)
    (grad_ref,) = torch.autograd.grad((reference * weights).sum(), encoding.table)
    assert torch.allclose(grad_ours, grad_ref, atol=1e-12)
    assert (grad_ours != 0).any(dim=1).sum() > 64  # the hashed rows are shared, and reached


def test_the_table_holds_each_level_once_at_its_size():
    encoding = HashEncoding(
        levels=16, features=2, log2_table_size=19, min_resolution=16, max_resolution=2048
    )
    # Instant-NGP's configuration: 16 levels of at most 2^19 entries of 2 features
    assert encoding.out_dim == 32
    sizes = [min((n + 1) ** 3, 2**19) for n in encoding.resolutions]
    assert encoding.table.shape == (sum(sizes), 2)
    assert encoding.table.abs().max() <= 1e-4


@pytest.mark.parametrize("order", [2.0, math.inf])
def test_the_contraction_is_the_identity_inside_continuous_at_the_unit_sphere_and_bounded(order):
    torch.manual_seed(2)
    inside = torch.rand(100, 3) - 0.5
    inside = inside / torch.linalg.vector_norm(inside, ord=order, dim=-1, keepdim=True) * 0.9
    assert torch.equal(contract(inside, order), inside)
    direction = torch.randn(100, 3, dtype=torch.float64)
    direction = direction / torch.linalg.vector_norm(direction, ord=order, dim=-1, keepdim=True)
    just_in, just_out = (
        contract(direction * (1 - 1e-9), order),
        contract(direction * (1 + 1e-9), order),
    )
    assert (just_in - just_out).abs().max() < 1e-8
    far = contract(direction * 1e12, order)
    norms = torch.linalg.vector_norm(far, ord=order, dim=-1)
    assert (norms < 2).all() and (norms > 2 - 1e-9).all()
    unit = contracted_unit(direction * torch.rand(100, 1, dtype=torch.float64) * 1e6, order)
    assert (unit >= 0).all() and (unit <= 1).all()
    # finite gradient at the origin (the unused branch is kept finite)
    origin = torch.zeros(1, 3, requires_grad=True)
    contract(origin, order).sum().backward()
    assert torch.isfinite(origin.grad).all()
