"""Operators at the scale of a capture's own resolution, checked on small problems cut into many
pieces: the assembly chunk by chunk into buffers that grow in place, the transpose built block
by block, the matrix-free adjoint block by block, and the size estimate that chooses between
them. Cutting a problem into pieces must not change a single entry."""

from __future__ import annotations

import re

import pytest
import torch

from flamerecon.operators import compiled, projector, residual_gradient, sparse
from flamerecon.operators.projector import MatrixFreeOperator, assemble, assembled_memory
from flamerecon.operators.sparse import CsrOperator, GrowingArray, transpose_csr
from tests.helpers import random_coo, random_hull, random_rays


@pytest.mark.parametrize("block", [1, 7, 10**9])
def test_the_transpose_by_blocks_is_the_transpose(monkeypatch, block):
    monkeypatch.setattr(sparse, "TRANSPOSE_BLOCK", block)
    op, matrix = random_coo(seed=3, N=60, M=45, nnz=500)
    A = op.A
    ccol, row, val = transpose_csr(A.crow_indices(), A.col_indices(), A.values(), op.shape[1])
    AT = torch.sparse_csr_tensor(ccol, row, val, size=(op.shape[1], op.shape[0]))
    assert torch.equal(AT.to_dense(), A.to_dense().T)  # every entry moved, none changed
    assert torch.allclose(AT.to_dense(), torch.from_numpy(matrix).T)
    for m in range(op.shape[1]):  # rows ascending within each column: the order products sum in
        rows = row[ccol[m]:ccol[m + 1]]
        assert bool((rows[1:] > rows[:-1]).all())


def test_a_matrix_with_empty_rows_and_columns_transposes(monkeypatch):
    monkeypatch.setattr(sparse, "TRANSPOSE_BLOCK", 2)
    rows, cols = torch.tensor([0, 0, 3, 5]), torch.tensor([4, 1, 1, 0])
    op = CsrOperator.from_coo(rows, cols, torch.tensor([1.0, 2.0, 3.0, 4.0]), (7, 6))
    assert torch.equal(op.AT.to_dense(), op.A.to_dense().T)
    empty = CsrOperator.from_coo(torch.zeros(0, dtype=torch.long), torch.zeros(0, dtype=torch.long),
                                 torch.zeros(0), (3, 2))
    assert empty.nnz == 0 and torch.equal(empty.AT.to_dense(), torch.zeros(2, 3))


@pytest.mark.parametrize("dtype", [torch.int32, torch.float32])
def test_a_growing_array_holds_its_pieces_in_order(dtype):
    buffer = GrowingArray(dtype, "cpu")
    pieces = [torch.arange(n, dtype=dtype) + 1000 * k for k, n in enumerate([0, 5, 70_000, 3, 200_000])]
    for piece in pieces:
        buffer.append(piece)
    out = buffer.tensor()
    assert out.dtype == dtype and torch.equal(out, torch.cat(pieces))


@pytest.mark.parametrize("chunk", [50, 997])
def test_assembly_chunk_by_chunk_gives_the_same_operator(monkeypatch, box_grid, chunk):
    rays = random_rays(box_grid, 400, seed=11)
    voxel_index = random_hull(box_grid, seed=12)
    whole = assemble(box_grid, rays, voxel_index)
    monkeypatch.setattr(projector, "ASSEMBLY_CHUNK_SAMPLES", chunk)
    monkeypatch.setattr(sparse, "TRANSPOSE_BLOCK", 64)
    pieces = assemble(box_grid, rays, voxel_index)
    for a, b in ((whole.A, pieces.A), (whole.AT, pieces.AT)):
        assert torch.equal(a.crow_indices(), b.crow_indices())
        assert torch.equal(a.col_indices(), b.col_indices())
        assert torch.equal(a.values(), b.values())  # the same sums in the same order
    assert whole.A.col_indices().dtype == torch.int32


def test_the_matrix_free_adjoint_by_blocks_is_the_whole_march_s(monkeypatch, box_grid):
    rays = random_rays(box_grid, 300, seed=13)
    voxel_index = random_hull(box_grid, seed=14)
    y = torch.randn(300, 2, generator=torch.Generator().manual_seed(15))
    op = MatrixFreeOperator(box_grid, rays, voxel_index)
    x = torch.zeros(op.shape[1], 2, requires_grad=True)
    (whole,) = torch.autograd.grad(op.forward(x), x, grad_outputs=y)  # one graph over every ray
    monkeypatch.setattr(projector, "CHUNK_SAMPLES", 100)  # dozens of blocks
    blocks = op.adjoint(y)
    assert (blocks - whole).abs().max() <= 1e-5 * whole.abs().max()
    assert (blocks - assemble(box_grid, rays, voxel_index).adjoint(y)).abs().max() <= 1e-5 * whole.abs().max()


def test_the_size_estimate_counts_the_nonzeros_from_a_few_rays(monkeypatch, box_grid):
    rays = random_rays(box_grid, 3000, seed=16)
    voxel_index = random_hull(box_grid, fraction=0.7, seed=17)
    nnz = assemble(box_grid, rays, voxel_index).nnz
    monkeypatch.setattr(projector, "ESTIMATE_RAYS", 300)  # every 10th ray
    est = assembled_memory(box_grid, rays, voxel_index)
    assert abs(est.nnz - nnz) <= 0.1 * nnz
    # int32 column + float32 value a nonzero, A^T too where the adjoint needs it (not on the compiled CPU path)
    assert est.copies == (1 if compiled.available("cpu") else 2) and est.operator_bytes >= 8 * est.copies * est.nnz
    assert est.peak_bytes > est.operator_bytes
    monkeypatch.setattr(projector, "ESTIMATE_RAYS", 10**6)  # every ray: exact
    assert assembled_memory(box_grid, rays, voxel_index).nnz == nnz


def test_a_stop_signal_inside_a_solve_ends_a_long_matrix_free_product_within_a_block(monkeypatch, box_grid):
    """Inside a solve a stop signal is only recorded (the guard checkpoints at its next check);
    a product that marches for minutes raises it between two of its blocks."""
    from flamerecon import interrupt

    rays = random_rays(box_grid, 300, seed=18)
    op = MatrixFreeOperator(box_grid, rays, random_hull(box_grid, seed=19))
    monkeypatch.setattr(projector, "CHUNK_SAMPLES", 100)  # dozens of blocks
    monkeypatch.setattr(compiled, "BLOCK_SEGMENTS", 100)  # the same for the compiled forward march
    blocks = []

    def counted(march):
        def marching(*args):
            blocks.append(1)
            if len(blocks) == 3:
                monkeypatch.setattr(interrupt, "_received", "SIGTERM")  # as the deferred handler records it
            return march(*args)
        return marching

    monkeypatch.setattr(projector, "_sample", counted(projector._sample))
    for kernel in ("rows_forward", "rows_adjoint"):  # the compiled march's products
        monkeypatch.setattr(compiled, kernel, counted(getattr(compiled, kernel)))
    for product in (op.forward, op.adjoint):
        blocks.clear()
        with pytest.raises(interrupt.Stopped, match="SIGTERM received"):
            product(torch.ones(op.shape[1 if product == op.forward else 0], 1))
        assert len(blocks) == 3  # stopped after the block the signal came in, not at the product's end


needs_numba = pytest.mark.skipif(not compiled.available("cpu"), reason="numba is not installed: the torch path serves")


@needs_numba
@pytest.mark.parametrize("block", [37, 10**9])
def test_the_compiled_assembly_is_the_torch_one_entry_for_entry(monkeypatch, box_grid, block):
    rays = random_rays(box_grid, 500, seed=21)
    voxel_index = random_hull(box_grid, seed=22)
    monkeypatch.setattr(compiled, "BLOCK_SEGMENTS", block)  # many blocks, or one
    fast = assemble(box_grid, rays, voxel_index)
    monkeypatch.setattr(compiled, "numba", None)
    slow = assemble(box_grid, rays, voxel_index)
    assert slow.nnz > 1000 and fast.nnz == slow.nnz
    assert torch.equal(fast.A.crow_indices(), slow.A.crow_indices())
    assert torch.equal(fast.A.col_indices(), slow.A.col_indices())
    assert torch.equal(fast.A.values(), slow.A.values())  # the same float operations, in march order


@needs_numba
@pytest.mark.parametrize(("threads", "channels"), [(1, 3), (2, 3), (2, 1), (2, 2)])  # 1 and 3: own paths
def test_the_compiled_adjoint_reads_a_rows_and_stores_no_transpose(threads, channels):
    op, matrix = random_coo(seed=5, N=300, M=80, nnz=4000)
    y = torch.randn(300, channels, generator=torch.Generator().manual_seed(6))
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(threads)
        got = op.adjoint(y)
    finally:
        torch.set_num_threads(before)
    assert not op.stores_transpose and op._AT is None  # A alone: half the operator's memory
    assert torch.allclose(got.double(), torch.from_numpy(matrix).double().T @ y.double(), rtol=1e-5, atol=1e-5)
    assert torch.equal(got, op.adjoint(y))  # the same sums whatever the threads: deterministic
    assert torch.allclose(got, op.AT @ y, rtol=1e-5, atol=1e-5)  # A^T, built on demand, agrees


@needs_numba
@pytest.mark.parametrize("channels", [1, 3])
def test_the_compiled_march_integrates_as_grid_sample_does(monkeypatch, box_grid, channels):
    rays = random_rays(box_grid, 400, seed=23)
    volume = torch.rand(channels, *box_grid.shape, generator=torch.Generator().manual_seed(24))
    box = projector.support_box(box_grid, random_hull(box_grid, seed=25))
    monkeypatch.setattr(compiled, "BLOCK_SEGMENTS", 50)  # many blocks
    for narrowed in (None, box):
        fast = projector.integrate_dense(volume, box_grid, rays, 0.5, narrowed)
        with monkeypatch.context() as torch_path:
            torch_path.setattr(compiled, "numba", None)
            slow = projector.integrate_dense(volume, box_grid, rays, 0.5, narrowed)
        assert fast.shape == (400, channels) and float(slow.abs().max()) > 0.1
        assert torch.allclose(fast, slow, rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("channels", [1, 2, 3])
def test_the_residual_and_its_gradient_in_one_pass_are_the_two_products(channels):
    op, matrix = random_coo(seed=7, N=250, M=90, nnz=3000)
    g = torch.Generator().manual_seed(8)
    x, b = torch.rand(90, channels, generator=g), torch.rand(250, channels, generator=g)
    r, grad = residual_gradient(op, x, b)
    dense = torch.from_numpy(matrix).double()
    expected_r = dense @ x.double() - b.double()
    assert torch.allclose(r.double(), expected_r, rtol=1e-5, atol=1e-5)
    assert torch.allclose(grad.double(), dense.T @ expected_r, rtol=1e-4, atol=1e-4)


def test_the_geometric_bound_holds_the_assembled_operator(box_grid):
    """The bound that spares the sampled estimate of a small operator is never below it."""
    rays = random_rays(box_grid, 600, seed=41)
    for seed in (42, 43):
        voxel_index = random_hull(box_grid, seed=seed)
        op = assemble(box_grid, rays, voxel_index)
        stored = op.nbytes() * (1 if not op.stores_transpose else 2)
        assert projector.assembled_bound(box_grid, rays, voxel_index) >= stored > 0
        assert projector.assembled_bound(box_grid, rays, voxel_index) >= assembled_memory(box_grid, rays,
                                                                                        voxel_index).peak_bytes


def test_an_assembled_operator_that_does_not_fit_is_refused_with_the_ways_out(box_grid, caplog):
    from flamerecon.errors import MemoryBudgetError
    from flamerecon.fit.checks import choose_backend

    rays, voxel_index = random_rays(box_grid, 600, seed=44), random_hull(box_grid, seed=45)
    with pytest.raises(MemoryBudgetError, match=r"^projector\.backend=assembled: the assembled operator for 600 rays "
                       r"x \d+ hull voxels needs about .* nonzeros.*use projector\.backend=matrix_free.*grid\.resolution"):
        choose_backend("assembled", box_grid, rays, voxel_index, 0.5, torch.device("cpu"), 1000)
    caplog.set_level("WARNING")
    assert choose_backend("auto", box_grid, rays, voxel_index, 0.5, torch.device("cpu"), 1000, 50) == "matrix_free"
    assert re.search(r"using the matrix-free backend, whose products march every ray again: about .* for 50 "
                     r"iterations here\. To keep the assembled one: free memory or raise projector\.max_memory_gb",
                     caplog.text)
