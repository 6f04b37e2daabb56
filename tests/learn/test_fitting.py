"""What the trainers share: the ridge solvers, the divergence guard, early stopping."""

import pytest
import torch

from dozerlab.learn.fitting import (
    EarlyStopping,
    NormalEquations,
    TrainingDiverged,
    adam,
    device_for,
    gram,
    guard,
    solve_ridge,
)
from dozerlab.runtime import DozerlabError

W = torch.tensor([[1.5, -2.0], [0.0, 0.5], [3.0, 1.0]], dtype=torch.float64)
B = torch.tensor([0.25, -1.0], dtype=torch.float64)


def _data(n: int, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    x = torch.randn(n, 3, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)
    return x, x @ W + B


def test_ridge_without_penalty_recovers_an_exact_linear_map():
    x, y = _data(50)
    w, b = solve_ridge(x, y, 0.0)
    torch.testing.assert_close(w, W, atol=1e-6, rtol=0)
    torch.testing.assert_close(b, B, atol=1e-6, rtol=0)
    # more features than samples: solved in the dual, still fitting every sample
    x2, y2 = _data(2)
    w2, b2 = solve_ridge(x2, y2, 0.0)
    torch.testing.assert_close(x2 @ w2 + b2, y2, atol=1e-6, rtol=0)


def test_the_penalty_shrinks_the_weights_and_a_negative_one_is_refused():
    x, y = _data(50)
    w, _ = solve_ridge(x, y, 10.0)
    assert w.norm() < 0.2 * W.norm()
    with pytest.raises(ValueError, match="ridge alpha must be >= 0, got -1"):
        solve_ridge(x, y, -1)


def test_normal_equations_in_chunks_match_the_whole_and_weights_repeat_rows():
    x, y = _data(60)
    y = y + 0.1 * torch.randn(60, 2, generator=torch.Generator().manual_seed(1), dtype=y.dtype)
    rows, targets = torch.cat([x, x[:10]]), torch.cat([y, y[:10]])  # the first ten rows twice
    whole, chunks, weighted = NormalEquations(3, 2), NormalEquations(3, 2), NormalEquations(3, 2)
    whole.add(rows, targets)
    for i in range(0, 70, 25):
        chunks.add(rows[i : i + 25], targets[i : i + 25])
    weight = torch.ones(60, dtype=torch.float64)
    weight[:10] = 2.0
    weighted.add(x, y, weight)
    for other in (chunks, weighted):
        for a, b in zip(whole.solve(0.01), other.solve(0.01), strict=True):
            torch.testing.assert_close(a, b, atol=1e-10, rtol=0)
    # without a penalty: the least-squares fit, as solve_ridge finds it
    for a, b in zip(whole.solve(0.0), solve_ridge(rows, targets, 0.0), strict=True):
        torch.testing.assert_close(a, b, atol=1e-6, rtol=0)


def test_rows_of_weight_zero_add_nothing_and_the_gram_is_the_full_product():
    x, y = _data(40)
    y = y + 0.1 * torch.randn(40, 2, generator=torch.Generator().manual_seed(2), dtype=y.dtype)
    weight = torch.rand(40, generator=torch.Generator().manual_seed(3), dtype=x.dtype)
    weight[::3] = 0.0
    kept, padded = NormalEquations(3, 2), NormalEquations(3, 2)
    kept.add(x[weight > 0], y[weight > 0], weight[weight > 0])
    wild = x.clone()
    wild[::3] = 1e6  # rows that would dominate every sum, at weight 0
    padded.add(wild, y, weight)
    for a, b in zip(kept.solve(0.01), padded.solve(0.01), strict=True):
        torch.testing.assert_close(a, b, atol=1e-10, rtol=0)
    for d in (3, 7, 963):
        for dtype, tol in ((torch.float64, 1e-9), (torch.float32, 1e-3)):
            z = torch.randn(30, d, generator=torch.Generator().manual_seed(d), dtype=dtype)
            want = z.T @ z
            got = gram(z[::2])  # a strided view: the rows are made contiguous first
            torch.testing.assert_close(got, z[::2].T @ z[::2], atol=tol, rtol=0)
            assert got.dtype == dtype and torch.equal(got, got.T)
            torch.testing.assert_close(gram(z), want, atol=tol, rtol=0)
    with pytest.raises(ValueError, match="weights must be >= 0"):
        kept.add(x, y, -weight)


def test_a_column_constant_in_float32_rows_gets_no_weight_whatever_the_chunks():
    # float32 products left a constant column a rounding-level variance; standardised, it
    # became unit noise the fit used, so the weights changed with the order of the sums
    gen = torch.Generator().manual_seed(4)
    x = torch.randn(3000, 3, generator=gen)
    y = (x.double() @ W + B).float() + 0.1 * torch.randn(3000, 2, generator=gen)
    rows = torch.cat([x, torch.full((3000, 1), 0.7)], 1)
    fits = []
    for chunk in (3000, 700, 128):
        eq = NormalEquations(4, 2)
        for i in range(0, 3000, chunk):
            eq.add(rows[i : i + chunk], y[i : i + chunk], torch.ones(len(rows[i : i + chunk])))
        fits.append(eq.solve(1e-3))
    plain = NormalEquations(3, 2)
    plain.add(x, y)
    want_w, want_b = plain.solve(1e-3)
    for w, b in fits:
        assert torch.equal(w[3], torch.zeros(2, dtype=w.dtype))
        torch.testing.assert_close(w[:3], want_w, atol=1e-5, rtol=0)
        torch.testing.assert_close(b, want_b, atol=1e-5, rtol=0)


def test_normal_equations_without_samples_are_refused():
    empty = NormalEquations(3, 2)
    x, y = _data(5)
    empty.add(x, y, torch.zeros(5, dtype=torch.float64))
    with pytest.raises(DozerlabError, match="without samples"):
        empty.solve(0.1)
    with pytest.raises(ValueError, match="ridge alpha must be >= 0"):
        empty.solve(-0.5)


def test_guard_names_what_diverged():
    guard(1e30, "the loss")  # large but finite: fine
    with pytest.raises(TrainingDiverged, match=r"training diverged: the loss is nan; .* lower the"):
        guard(float("nan"), "the loss")
    with pytest.raises(TrainingDiverged, match=r"is inf; .* raise the ridge alpha"):
        guard(float("inf"), "w", "raise the ridge alpha")


def test_early_stopping_waits_patience_epochs_and_restores_the_best_state():
    model = torch.nn.Linear(2, 1)
    seen = []
    stop = EarlyStopping(model, patience=2, on_epoch=lambda *a: seen.append(a))
    stops = []
    for epoch, val in enumerate([3.0, 2.0, 2.5, 2.6]):
        with torch.no_grad():
            model.bias.fill_(float(epoch))
        stops.append(stop.end_epoch(epoch, 10.0 - epoch, val))
    assert stops == [False, False, False, True]
    assert (stop.best, stop.best_epoch) == (2.0, 1) and seen[1] == (1, 9.0, 2.0)
    assert stop.val_loss == [3.0, 2.0, 2.5, 2.6]
    stop.restore()
    assert model.bias.item() == 1.0


def test_device_is_the_named_one_or_the_best_present():
    assert device_for("cpu") == torch.device("cpu")
    assert device_for().type == ("cuda" if torch.cuda.is_available() else "cpu")


def test_fused_adam_takes_the_reference_adam_steps():
    def steps(make_opt):  # type: ignore[no-untyped-def]
        torch.manual_seed(0)
        model = torch.nn.Sequential(torch.nn.Linear(7, 5), torch.nn.GELU(), torch.nn.Linear(5, 2))
        opt = make_opt(model.parameters())
        x, y = torch.randn(16, 7), torch.randn(16, 2)
        for _ in range(5):
            opt.zero_grad()
            torch.nn.functional.mse_loss(model(x), y).backward()
            opt.step()
        return [p.detach().clone() for p in model.parameters()]

    fused = steps(lambda p: adam(p, 1e-2, 1e-3))
    reference = steps(lambda p: torch.optim.Adam(p, lr=1e-2, weight_decay=1e-3, foreach=False))
    assert any(
        not torch.equal(a, b) for a, b in zip(fused, steps(lambda p: adam(p, 1e-2)), strict=True)
    )
    for a, b in zip(fused, reference, strict=True):
        torch.testing.assert_close(a, b, atol=1e-6, rtol=1e-5)
