"""JAX SMO SVMs against scikit-learn (libsvm), solver invariants, padding, vmap, edge cases."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from dscpp_jax import svm
from tests.svm_data import dsc_like

sklearn_svm = pytest.importorskip("sklearn.svm")

GAMMA = 0.5
SLOTS = 5248  # fits the largest fixture (100 trajectories x 51 + 100 negatives)


def fixture_data(name):
    if name == "overlap":  # space-filling, overlapping classes
        rng = np.random.default_rng(7)
        X = rng.uniform(-3, 3, (600, 2)).astype(np.float32)
        p = 1 / (1 + np.exp(-2.0 * (X[:, 0] + 0.5 * np.sin(2 * X[:, 1]))))
        lab = (rng.uniform(size=600) < p).astype(np.int32)
        return X[lab == 1], X[lab == 0]
    n_traj, n_neg = name
    return dsc_like(1000 * n_traj + n_neg, n_traj, n_neg)


def padded(X, n_slots, labels=None, scatter_seed=None):
    """Padded copy; with scatter_seed the valid rows land at random slots (holes in the mask)."""
    n = len(X)
    slots = np.arange(n) if scatter_seed is None else np.sort(
        np.random.default_rng(scatter_seed).choice(n_slots, n, replace=False))
    Xp = np.full((n_slots, X.shape[1]), np.nan, np.float32)  # junk in padding on purpose
    Xp[slots] = X
    m = np.zeros(n_slots, bool)
    m[slots] = True
    if labels is None:
        return Xp, m
    lp = np.ones(n_slots, np.int32)
    lp[slots] = labels
    return Xp, lp, m


def grid(X, n=200):
    lo, hi = X.min(0) - 1.0, X.max(0) + 1.0
    g = np.stack(np.meshgrid(np.linspace(lo[0], hi[0], n), np.linspace(lo[1], hi[1], n)), -1)
    return g.reshape(-1, 2).astype(np.float32)


def svc_case(name):
    pos, neg = fixture_data(name)
    X = np.concatenate([pos, neg])
    lab = np.r_[np.ones(len(pos)), np.zeros(len(neg))].astype(np.int32)
    cw = "balanced" if len(neg) >= 10 else None
    return X, lab, cw


def class_C(lab, cw, C=1.0):
    if cw is None:
        return np.full(len(lab), C)
    n, n1 = len(lab), lab.sum()
    return np.where(lab == 1, C * n / (2 * n1), C * n / (2 * (n - n1)))


CASES = [(5, 3), (20, 10), (100, 100), "overlap"]


@pytest.mark.parametrize("name", CASES, ids=str)
def test_svc_matches_sklearn_and_invariants(name):
    X, lab, cw = svc_case(name)
    sk = sklearn_svm.SVC(kernel="rbf", gamma=GAMMA, C=1.0, class_weight=cw).fit(X, lab)
    Xp, lp, m = padded(X, SLOTS, lab, scatter_seed=1)
    model = svm.fit_svc(Xp, lp, m, gamma=GAMMA, C=1.0, class_weight=cw)
    g = grid(X)
    f_sk = sk.decision_function(g)
    f = np.asarray(svm.decision_function(model, g))
    assert np.mean((f >= 0) == (f_sk >= 0)) >= 0.999
    sure = np.abs(f_sk) > 1e-2
    assert np.all((f >= 0)[sure] == (f_sk >= 0)[sure])
    assert np.max(np.abs(f - f_sk)) <= 2e-2
    assert abs(float(model.rho) - (-sk.intercept_[0])) <= 5e-3
    assert np.mean(np.asarray(svm.predict(model, X)) == (sk.predict(X) == 1)) >= 0.999
    it_sk = int(np.sum(sk.n_iter_))
    assert abs(int(model.n_iter) - it_sk) <= 0.25 * it_sk + 5  # same algorithm, same path
    # solver invariants
    coef = np.asarray(model.coef)
    alpha = np.abs(coef)
    Cfull = np.zeros(SLOTS)
    Cfull[m] = class_C(lab, cw)
    assert bool(model.converged) and float(model.gap) < 1e-3
    assert np.all(alpha >= 0) and np.all(alpha <= Cfull * (1 + 1e-6) + 1e-7)
    assert np.all(coef[~m] == 0)
    assert abs(coef.sum()) <= 1e-3  # y^T alpha = 0
    assert np.all(np.sign(coef[m][coef[m] != 0]) == np.where(lab == 1, 1, -1)[coef[m] != 0])


@pytest.mark.parametrize("name", [(5, 3), (20, 10), (100, 100)], ids=str)
@pytest.mark.parametrize("nu", [0.1, 0.01])
def test_one_class_matches_sklearn_and_invariants(name, nu):
    pos, _ = fixture_data(name)
    sk = sklearn_svm.OneClassSVM(kernel="rbf", gamma=GAMMA, nu=nu).fit(pos)
    Xp, m = padded(pos, SLOTS)
    model = svm.fit_one_class(Xp, m, nu=nu, gamma=GAMMA)
    assert abs(float(model.rho) - sk.offset_[0]) / abs(sk.offset_[0]) <= 1e-3
    g = grid(pos)
    f_sk = sk.decision_function(g)
    f = np.asarray(svm.decision_function(model, g))
    sure = np.abs(f_sk) > 1e-2 * np.abs(f_sk).max()
    assert np.all((f > 0)[sure] == (f_sk > 0)[sure])
    it_sk = int(np.sum(sk.n_iter_))
    assert abs(int(model.n_iter) - it_sk) <= 0.25 * it_sk + 5
    alpha = np.asarray(model.coef)
    assert bool(model.converged)
    assert np.all(alpha >= 0) and np.all(alpha <= 1 + 1e-6) and np.all(alpha[~m] == 0)
    assert abs(alpha.sum() - nu * len(pos)) <= 1e-3 * max(1.0, nu * len(pos))


def test_padding_size_and_slot_positions_do_not_change_decisions():
    """1,024 vs 5,248 slots, valid rows packed first or scattered among NaN padding."""
    X, lab, cw = svc_case((5, 3))
    g = grid(X, 60)
    fs, gs = [], []
    for slots, seed in ((1024, None), (SLOTS, None), (1024, 3)):
        Xp, lp, m = padded(X, slots, lab, scatter_seed=seed)
        fs.append(np.asarray(svm.decision_function(svm.fit_svc(Xp, lp, m, gamma=GAMMA, class_weight=cw), g)))
        Xp, m = padded(X, slots, scatter_seed=seed)
        gs.append(np.asarray(svm.decision_function(svm.fit_one_class(Xp, m, nu=0.1, gamma=GAMMA), g)))
    for f in fs[1:]:
        assert np.max(np.abs(f - fs[0])) < 1e-3
        sure = np.abs(fs[0]) > 1e-3
        assert np.all((f >= 0)[sure] == (fs[0] >= 0)[sure])
    for f in gs[1:]:
        assert np.max(np.abs(f - gs[0])) < 1e-3 * np.abs(gs[0]).max()


def test_vmapped_batch_matches_single_fits():
    """Problems of different valid sizes in one vmapped call give the single fits' decisions."""
    names = [(5, 3), (12, 6), "overlap"]
    data = [svc_case(nm) for nm in names]
    Xs, Ls, Ms = zip(*[padded(X, 1024, lab, scatter_seed=i) for i, (X, lab, _) in enumerate(data)])
    bal = np.array([cw is not None for _, _, cw in data])
    fit_b = jax.vmap(lambda x, l, m, b: svm.fit_svc(x, l, m, gamma=GAMMA, class_weight=b))
    batch = fit_b(np.stack(Xs), np.stack(Ls), np.stack(Ms), bal)
    oc_b = jax.vmap(lambda x, m: svm.fit_one_class(x, m & (x[:, 0] > -2.0), nu=0.1, gamma=GAMMA))
    batch_oc = oc_b(np.stack(Xs), np.stack(Ms))
    assert np.asarray(batch.converged).all() and np.asarray(batch_oc.converged).all()
    assert len(set(np.asarray(batch.n_iter).tolist())) > 1  # they really stopped at different steps
    for k, (X, lab, cw) in enumerate(data):
        g = grid(X, 60)
        single = svm.fit_svc(Xs[k], Ls[k], Ms[k], gamma=GAMMA, class_weight=cw)
        bk = jax.tree.map(lambda a: a[k], batch)
        f1, fb = (np.asarray(svm.decision_function(mo, g)) for mo in (single, bk))
        sure = np.abs(f1) > 1e-3
        assert np.all((fb >= 0)[sure] == (f1 >= 0)[sure]) and np.max(np.abs(fb - f1)) < 1e-3
        single_oc = svm.fit_one_class(Xs[k], Ms[k] & (Xs[k][:, 0] > -2.0), nu=0.1, gamma=GAMMA)
        ok = jax.tree.map(lambda a: a[k], batch_oc)
        f1, fb = (np.asarray(svm.decision_function(mo, g)) for mo in (single_oc, ok))
        assert np.max(np.abs(fb - f1)) < 1e-3 * max(1.0, np.abs(f1).max())


def test_no_retrace_across_valid_counts():
    traces = []

    @jax.jit
    def fit(x, l, m):
        traces.append(1)
        return svm.fit_svc(x, l, m, gamma=GAMMA, class_weight="balanced").rho

    rng = np.random.default_rng(0)
    X = rng.normal(size=(128, 2)).astype(np.float32)
    lab = (X[:, 0] > 0).astype(np.int32)
    for n in (40, 100, 128):
        fit(X, lab, np.arange(128) < n).block_until_ready()
    assert len(traces) == 1
    before = svm._fit_one_class_jit._cache_size()
    for n in (30, 77, 120):  # eager public calls reuse one compiled solver too
        svm.fit_one_class(X, np.arange(128) < n, nu=0.1, gamma=GAMMA)
    assert svm._fit_one_class_jit._cache_size() - before <= 1


def test_single_class_gives_a_constant_classifier():
    X = np.random.default_rng(1).normal(size=(128, 2)).astype(np.float32)
    q = np.random.default_rng(2).normal(size=(50, 2)).astype(np.float32) * 3
    m = np.arange(128) < 40
    only_pos = svm.fit_svc(X, np.ones(128, np.int32), m, gamma=GAMMA)
    only_neg = svm.fit_svc(X, np.zeros(128, np.int32), m, gamma=GAMMA)
    empty = svm.fit_svc(X, np.ones(128, np.int32), np.zeros(128, bool), gamma=GAMMA)
    np.testing.assert_allclose(svm.decision_function(only_pos, q), 1.0)
    np.testing.assert_allclose(svm.decision_function(only_neg, q), -1.0)
    assert not np.asarray(svm.predict(empty, q)).any()
    assert not np.asarray(svm.predict(svm.fit_one_class(X, np.zeros(128, bool), nu=0.1, gamma=GAMMA), q)).any()


@pytest.mark.parametrize("kind", ["nu_l_below_one", "duplicates", "identical"])
def test_edge_cases_match_sklearn(kind):
    rng = np.random.default_rng(5)
    if kind == "nu_l_below_one":  # nu * l = 0.5: a single fractional alpha
        pos = rng.normal(size=(5, 2)).astype(np.float32)
        neg = rng.normal(3, 1, size=(4, 2)).astype(np.float32)
    elif kind == "duplicates":
        pos = np.repeat(rng.normal(size=(30, 2)), 2, axis=0).astype(np.float32)
        neg = np.repeat(rng.normal(2.5, 1, size=(12, 2)), 3, axis=0).astype(np.float32)
    else:  # all points identical (one-class) / two identical clusters (SVC)
        pos = np.full((20, 2), 0.7, np.float32)
        neg = np.full((12, 2), -1.0, np.float32)
    g = grid(np.concatenate([pos, neg]), 50)
    # one-class
    sk = sklearn_svm.OneClassSVM(kernel="rbf", gamma=GAMMA, nu=0.1).fit(pos)
    Xp, m = padded(pos, 128)
    mo = svm.fit_one_class(Xp, m, nu=0.1, gamma=GAMMA)
    assert bool(mo.converged)
    np.testing.assert_allclose(float(mo.rho), sk.offset_[0], rtol=1e-3, atol=1e-5)
    np.testing.assert_allclose(svm.decision_function(mo, g), sk.decision_function(g), atol=2e-3)
    # two-class
    X = np.concatenate([pos, neg])
    lab = np.r_[np.ones(len(pos)), np.zeros(len(neg))].astype(np.int32)
    cw = "balanced" if len(neg) >= 10 else None
    sk2 = sklearn_svm.SVC(kernel="rbf", gamma=GAMMA, C=1.0, class_weight=cw).fit(X, lab)
    Xp, lp, m = padded(X, 128, lab)
    mo2 = svm.fit_svc(Xp, lp, m, gamma=GAMMA, class_weight=cw)
    assert bool(mo2.converged)
    f_sk = sk2.decision_function(g)
    f = np.asarray(svm.decision_function(mo2, g))
    assert np.max(np.abs(f - f_sk)) <= 2e-2
    sure = np.abs(f_sk) > 1e-2
    assert np.all((f >= 0)[sure] == (f_sk >= 0)[sure])


def test_iteration_cap_reports_non_convergence():
    X, lab, cw = svc_case("overlap")
    Xp, lp, m = padded(X[::5], 128, lab[::5])  # 120 points of both classes
    mo = svm.fit_svc(Xp, lp, m, gamma=GAMMA, class_weight=cw, max_iter=5)
    assert int(mo.n_iter) == 5 and not bool(mo.converged) and float(mo.gap) >= 1e-3


def test_bad_arguments_raise():
    X = np.zeros((8, 2), np.float32)
    lab = np.ones(8, np.int32)
    m = np.ones(8, bool)
    with pytest.raises(ValueError, match="nu"):
        svm.fit_one_class(X, m, nu=0.0, gamma=GAMMA)
    with pytest.raises(ValueError, match="nu"):
        svm.fit_one_class(X, m, nu=1.5, gamma=GAMMA)
    with pytest.raises(ValueError, match="gamma"):
        svm.fit_svc(X, lab, m, gamma=0.0)
    with pytest.raises(ValueError, match="gamma"):
        svm.fit_one_class(X, m, nu=0.1, gamma=-1.0)
    with pytest.raises(ValueError, match="labels"):
        svm.fit_svc(X, lab[:5], m, gamma=GAMMA)
    with pytest.raises(ValueError, match="mask"):
        svm.fit_one_class(X, m[:3], nu=0.1, gamma=GAMMA)
    with pytest.raises(ValueError, match="X"):
        svm.fit_one_class(X[:, 0], m, nu=0.1, gamma=GAMMA)
    with pytest.raises(ValueError, match="class_weight"):
        svm.fit_svc(X, lab, m, gamma=GAMMA, class_weight="auto")
    with pytest.raises(ValueError, match="max_iter"):
        svm.fit_svc(X, lab, m, gamma=GAMMA, max_iter=0)
    mo = svm.fit_one_class(X, m, nu=0.5, gamma=GAMMA)
    with pytest.raises(ValueError, match="features"):
        svm.decision_function(mo, np.zeros((3, 3), np.float32))


# --------------------------------------------------------------------------------------------
# The fused Pallas kernel (interpret mode on a CPU): the XLA loop's path, the same decisions

# Small chunks so that the small fixtures take both of the kernel's paths: swept in chunks of 128
# points (3 chunks for 258 points), or kept in registers (up to 512 points, 8 steps per block).
SWEPT = svm.Solver(backend="pallas", chunk=128, resident=0)
RESIDENT = svm.Solver(backend="pallas", chunk=128, resident=512, steps=8)


def assert_same_fit(a, b, g):
    """The same problem solved by both backends: the same steps and model up to float rounding
    (the interpreted kernel matches the XLA loop bit for bit on XLA:CPU; GPUs round exp
    differently, which can reorder near-ties late in the run)."""
    assert abs(int(a.n_iter) - int(b.n_iter)) <= 0.1 * int(b.n_iter) + 3
    assert bool(a.converged) and bool(b.converged)
    fa, fb = (np.asarray(svm.decision_function(m, g)) for m in (a, b))
    scale = max(1.0, float(np.abs(fb).max()))
    assert np.max(np.abs(fa - fb)) <= 5e-3 * scale
    assert abs(float(a.rho) - float(b.rho)) <= 5e-3 * scale
    sure = np.abs(fb) > 1e-2 * scale
    assert np.all((fa > 0)[sure] == (fb > 0)[sure])


@pytest.mark.parametrize("solver", [SWEPT, RESIDENT], ids=["swept", "resident"])
def test_pallas_kernel_matches_xla_loop_and_sklearn(solver):
    X, lab, cw = svc_case((5, 3))  # 258 points scattered over 512 slots
    g = grid(X, 100)
    Xp, lp, m = padded(X, 512, lab, scatter_seed=2)
    pal = svm.fit_svc(Xp, lp, m, gamma=GAMMA, class_weight=cw, _inner=solver)
    assert_same_fit(pal, svm.fit_svc(Xp, lp, m, gamma=GAMMA, class_weight=cw, backend="xla"), g)
    sk = sklearn_svm.SVC(kernel="rbf", gamma=GAMMA, C=1.0, class_weight=cw).fit(X, lab)
    f_sk, f = sk.decision_function(g), np.asarray(svm.decision_function(pal, g))
    sure = np.abs(f_sk) > 1e-2
    assert np.all((f >= 0)[sure] == (f_sk >= 0)[sure]) and np.max(np.abs(f - f_sk)) <= 2e-2
    assert abs(float(pal.rho) - (-sk.intercept_[0])) <= 5e-3
    assert np.all(np.asarray(pal.coef)[~m] == 0)

    Xp, m = padded(X[lab == 1], 512, scatter_seed=3)
    pal = svm.fit_one_class(Xp, m, nu=0.1, gamma=GAMMA, _inner=solver)
    assert_same_fit(pal, svm.fit_one_class(Xp, m, nu=0.1, gamma=GAMMA, backend="xla"), g)
    sk = sklearn_svm.OneClassSVM(kernel="rbf", gamma=GAMMA, nu=0.1).fit(X[lab == 1])
    assert abs(float(pal.rho) - sk.offset_[0]) / abs(sk.offset_[0]) <= 1e-3
    f_sk, f = sk.decision_function(g), np.asarray(svm.decision_function(pal, g))
    sure = np.abs(f_sk) > 1e-2 * np.abs(f_sk).max()
    assert np.all((f > 0)[sure] == (f_sk > 0)[sure])
    assert abs(float(np.sum(pal.coef)) - 0.1 * int(m.sum())) <= 1e-3 * max(1.0, 0.1 * int(m.sum()))


def test_pallas_kernel_vmapped_batch_matches_xla_loop():
    """One kernel program per problem: sizes on both sides of the register limit (one problem
    in registers, one swept), finishing at different steps."""
    data = [svc_case(nm) for nm in [(2, 3), (4, 12)]]  # 105 and 216 points
    Xs, Ls, Ms = map(np.stack, zip(*[padded(X, 256, lab, scatter_seed=i) for i, (X, lab, _) in enumerate(data)]))
    bal = np.array([cw is not None for _, _, cw in data])

    def fit(sv):
        return jax.vmap(lambda x, l, m, b: svm.fit_svc(x, l, m, gamma=GAMMA, class_weight=b, _inner=sv))(Xs, Ls, Ms, bal)

    got = fit(svm.Solver(backend="pallas", chunk=64, resident=128, steps=4, variadic=True))
    want = fit(svm.resolve_inner(None, "xla"))
    assert len(set(np.asarray(got.n_iter).tolist())) > 1
    for k, (X, _, _) in enumerate(data):
        assert_same_fit(*(jax.tree.map(lambda a: a[k], mo) for mo in (got, want)), grid(X, 60))


def test_pallas_backend_edge_cases_and_arguments():
    X = np.random.default_rng(1).normal(size=(128, 2)).astype(np.float32)
    q = np.random.default_rng(2).normal(size=(50, 2)).astype(np.float32) * 3
    m = np.arange(128) < 40
    lab = (X[:, 0] > 0).astype(np.int32)
    only_pos = svm.fit_svc(X, np.ones(128, np.int32), m, gamma=GAMMA, max_iter=3, _inner=RESIDENT)
    np.testing.assert_allclose(svm.decision_function(only_pos, q), 1.0)
    empty = svm.fit_one_class(X, np.zeros(128, bool), nu=0.1, gamma=GAMMA, backend="pallas")
    assert int(empty.n_iter) == 0 and not np.asarray(svm.predict(empty, q)).any()
    for sv in (SWEPT, RESIDENT):  # the cap stops mid-block in registers too
        capped = svm.fit_svc(X, lab, m, gamma=GAMMA, max_iter=3, _inner=sv)
        assert int(capped.n_iter) == 3 and not bool(capped.converged) and float(capped.gap) >= 1e-3
    with pytest.raises(ValueError, match="backend"):
        svm.fit_svc(X, lab, m, gamma=GAMMA, backend="cuda")
    with pytest.raises(ValueError, match="chunk"):
        svm.fit_one_class(X, m, nu=0.1, gamma=GAMMA, _inner=SWEPT._replace(chunk=100))
    with pytest.raises(ValueError, match="resident"):
        svm.fit_one_class(X, m, nu=0.1, gamma=GAMMA, _inner=SWEPT._replace(resident=1000))
