"""Dual (DSC++) and single (baseline DSC) initiation classifiers against a scikit-learn pipeline."""

import jax
import numpy as np
import pytest

from dscpp_jax import initiation as ini
from dscpp_jax import svm
from tests.svm_data import dsc_like

sklearn_svm = pytest.importorskip("sklearn.svm")

P, M = 1024, 32  # positive / negative slots
CFG = ini.InitiationConfig()
SINGLE = ini.InitiationConfig(variant="single")


def pad(a, n):
    out = np.zeros((n, 2), np.float32)
    out[: len(a)] = a
    return out, np.arange(n) < len(a)


def padded(pos, neg):
    return (*pad(pos, P), *pad(neg, M))


def grid(pos, neg, n=120):
    X = np.concatenate([pos, neg])
    lo, hi = X.min(0) - 1.0, X.max(0) + 1.0
    g = np.stack(np.meshgrid(np.linspace(lo[0], hi[0], n), np.linspace(lo[1], hi[1], n)), -1)
    return g.reshape(-1, 2).astype(np.float32)


def sk_svc(pos, neg):
    X = np.concatenate([pos, neg])
    y = np.r_[np.ones(len(pos)), np.zeros(len(neg))]
    cw = "balanced" if len(neg) >= 10 else None
    return sklearn_svm.SVC(kernel="rbf", gamma=0.5, C=1.0, class_weight=cw).fit(X, y)


def sk_occ(X, nu):
    return sklearn_svm.OneClassSVM(kernel="rbf", gamma=0.5, nu=nu).fit(X)


def agree_where_sure(inside, f_sk, two_class):
    """Decision agreement away from the boundary (ties at f = 0 may flip either way)."""
    sure = np.abs(f_sk) > (1e-2 if two_class else 1e-2 * np.abs(f_sk).max())
    ref = f_sk >= 0 if two_class else f_sk > 0
    return np.all(inside[sure] == ref[sure]), np.mean(inside == ref)


CASES = {"few_negatives": (5, 3), "balanced": (20, 10), "positives_only": (12, 0)}


ALL = ini.InitiationConfig(pessimistic_examples="all")


@pytest.mark.parametrize("case,cfg", [(c, CFG) for c in CASES] + [("overlapping", ALL)],
                         ids=lambda v: v if isinstance(v, str) else v.pessimistic_examples)
def test_dual_classifiers_match_sklearn_pipeline(case, cfg):
    if case == "overlapping":  # negatives among the positives: some are called positive
        pos, neg = overlapping()
    else:
        pos, neg = dsc_like(sum(CASES[case]), *CASES[case])
    clf = ini.fit_initiation(*padded(pos, neg), cfg)
    g = grid(pos, neg)
    if len(neg):
        svc = sk_svc(pos, neg)
        f_opt = svc.decision_function(g)
        X = np.concatenate([pos, neg]) if cfg.pessimistic_examples == "all" else pos
        called = X[svc.predict(X) == 1]
        if case == "overlapping":
            assert len(called) > np.sum(svc.predict(pos) == 1)  # the switch matters here
        occ = sk_occ(called, 0.1)
    else:
        f_opt = sk_occ(pos, 0.01).decision_function(g)
        occ = sk_occ(pos, 0.1)
    opt = np.asarray(ini.optimistic_contains(clf, g))
    pes = np.asarray(ini.pessimistic_contains(clf, g))
    sure_ok, frac = agree_where_sure(opt, f_opt, two_class=len(neg) > 0)
    assert sure_ok and frac >= 0.999
    sure_ok, frac = agree_where_sure(pes, occ.decision_function(g), two_class=False)
    assert sure_ok and frac >= 0.999
    assert bool(clf.optimistic_fitted) and bool(clf.pessimistic_fitted)
    assert bool(clf.optimistic.one_class) == (len(neg) == 0) and bool(clf.pessimistic.one_class)
    np.testing.assert_array_equal(np.asarray(ini.initiation_contains(clf, g)), opt | pes)
    # the pessimistic region is the tight one
    assert pes.sum() < opt.sum() or len(neg) > 0


def overlapping():
    """Negatives among the positives: the SVC calls some of them positive."""
    pos, _ = dsc_like(4, 6, 0)
    return pos, np.concatenate([pos[::16] + 0.3, dsc_like(5, 1, 12)[1]])


@pytest.mark.parametrize("case", ["few_negatives", "balanced", "positives_only", "overlapping"])
def test_single_variant_is_use_pessimistic_clf_only(case):
    """The authors' `use_pessimistic_clf_only`: one one-class SVM (nu 0.1) fit on the points,
    positives and negatives together, that the two-class SVC calls positive (on the positives
    when there are no negatives); it is both the initiation set and the child's target."""
    pos, neg = overlapping() if case == "overlapping" else dsc_like(sum(CASES[case]), *CASES[case])
    clf = ini.fit_initiation(*padded(pos, neg), SINGLE)
    g = grid(pos, neg)
    if len(neg):
        X = np.concatenate([pos, neg])
        called = X[sk_svc(pos, neg).predict(X) == 1]
        if case == "overlapping":
            assert len(called) > np.sum(sk_svc(pos, neg).predict(pos) == 1)  # negatives enter
        occ = sk_occ(called, 0.1)
    else:
        occ = sk_occ(pos, 0.1)
    inside = np.asarray(ini.initiation_contains(clf, g))
    sure_ok, frac = agree_where_sure(inside, occ.decision_function(g), two_class=False)
    assert sure_ok and frac >= 0.999
    assert bool(clf.pessimistic.one_class) and bool(clf.optimistic.one_class)
    # one classifier: the target region (pessimistic) is the initiation set itself
    np.testing.assert_array_equal(np.asarray(ini.pessimistic_contains(clf, g)), inside)
    np.testing.assert_array_equal(np.asarray(ini.optimistic_contains(clf, g)), inside)
    jax.tree.map(np.testing.assert_array_equal, clf.optimistic, clf.pessimistic)


def test_single_variant_keeps_its_model_when_the_svc_calls_nothing_positive():
    pos, neg = dsc_like(3, 5, 3)
    g = grid(pos, neg, 40)
    prev = ini.fit_initiation(*padded(pos, neg), SINGLE)
    lone, crowd = np.zeros((1, 2), np.float32), np.zeros((9, 2), np.float32)
    X = np.concatenate([lone, crowd])
    assert not np.any(sk_svc(lone, crowd).predict(X) == 1)
    out = ini.fit_initiation(*padded(lone, crowd), SINGLE, prev=prev)
    jax.tree.map(np.testing.assert_array_equal, out, prev)
    fresh = ini.fit_initiation(*padded(lone, crowd), SINGLE)
    assert not bool(fresh.optimistic_fitted) and not bool(fresh.pessimistic_fitted)
    assert not np.asarray(ini.initiation_contains(fresh, g)).any()


def test_unfitted_contains_nothing_and_previous_models_are_kept():
    pos, neg = dsc_like(3, 5, 3)
    g = grid(pos, neg, 40)
    empty = ini.empty_initiation(P, M)
    for fn in (ini.initiation_contains, ini.optimistic_contains, ini.pessimistic_contains):
        assert not np.asarray(fn(empty, g)).any()
    # only negatives: nothing to fit, the (unfitted / previous) classifiers stay
    none = ini.fit_initiation(*pad(pos[:0], P), *pad(neg, M), CFG)
    assert not np.asarray(ini.initiation_contains(none, g)).any()
    prev = ini.fit_initiation(*padded(pos, neg), CFG)
    kept = ini.fit_initiation(*pad(pos[:0], P), *pad(neg, M), CFG, prev=prev)
    jax.tree.map(np.testing.assert_array_equal, kept, prev)
    # a positive the SVC itself calls negative (9 failures from the same spot, no balancing):
    # the optimistic model is refit, the pessimistic one is kept
    lone, crowd = np.zeros((1, 2), np.float32), np.zeros((9, 2), np.float32)
    assert sk_svc(lone, crowd).predict(lone)[0] == 0
    out = ini.fit_initiation(*padded(lone, crowd), CFG, prev=prev)
    jax.tree.map(np.testing.assert_array_equal, out.pessimistic, prev.pessimistic)
    assert bool(out.pessimistic_fitted)
    assert not np.asarray(ini.optimistic_contains(out, g)).any()
    fresh = ini.fit_initiation(*padded(lone, crowd), CFG)
    assert bool(fresh.optimistic_fitted) and not bool(fresh.pessimistic_fitted)
    assert not np.asarray(ini.initiation_contains(fresh, g)).any()


def test_batch_refit_matches_single_fits_and_keeps_clean_rows(monkeypatch):
    data = [dsc_like(10 + k, *c) for k, c in enumerate(CASES.values())]
    batch = [np.stack(a) for a in zip(*[padded(p, n) for p, n in data])]
    dirty = np.array([True, False, True])
    # the accelerator path (one vmapped SMO loop) here, the CPU path (lax.map) below
    monkeypatch.setitem(ini.BATCH_MODE, jax.default_backend(), "vmap")
    out = ini.fit_initiation_batch(*batch, CFG, dirty=dirty)
    monkeypatch.setitem(ini.BATCH_MODE, jax.default_backend(), "map")
    assert np.asarray(out.optimistic_fitted).tolist() == [True, False, True]
    for k in (0, 2):
        one = ini.fit_initiation(*[a[k] for a in batch], CFG)
        ok = jax.tree.map(lambda a: a[k], out)
        g = grid(*data[k], 60)
        for fn in (ini.optimistic_contains, ini.pessimistic_contains):
            f1 = np.asarray(svm.decision_function((one.optimistic if fn is ini.optimistic_contains
                                                   else one.pessimistic), g))
            sure = np.abs(f1) > 1e-3 * max(1.0, np.abs(f1).max())
            assert np.all(np.asarray(fn(ok, g))[sure] == np.asarray(fn(one, g))[sure])
    # refit row 1 only: rows 0 and 2 stay bit-identical even though their data changed
    shuffled = [a.copy() for a in batch]
    shuffled[0][0] = shuffled[0][0][::-1]
    again = ini.fit_initiation_batch(*shuffled, CFG, prev=out, dirty=np.array([False, True, False]))
    for k in (0, 2):
        jax.tree.map(np.testing.assert_array_equal, jax.tree.map(lambda a: a[k], again),
                     jax.tree.map(lambda a: a[k], out))
    assert bool(again.optimistic_fitted[1]) and bool(again.pessimistic_fitted[1])


def test_no_retrace_across_example_counts():
    traces = []

    @jax.jit
    def refit(pos, pm, neg, nm):
        traces.append(1)
        clf = ini.fit_initiation(pos, pm, neg, nm, CFG)
        return ini.initiation_contains(clf, pos[:4])

    pos, neg = dsc_like(5, 20, 30)
    for n_pos, n_neg in ((51, 0), (300, 4), (1020, 30)):  # one-class path, SVC, balanced SVC
        refit(*pad(pos[:n_pos], P), *pad(neg[:n_neg], M)).block_until_ready()
    assert len(traces) == 1


def test_bad_config_and_shapes_raise():
    with pytest.raises(ValueError, match="variant"):
        ini.InitiationConfig(variant="triple")
    with pytest.raises(ValueError, match="nu_pessimistic"):
        ini.InitiationConfig(nu_pessimistic=0.0)
    with pytest.raises(ValueError, match="gamma"):
        ini.InitiationConfig(gamma=0.0)
    with pytest.raises(ValueError, match="pessimistic_examples"):
        ini.InitiationConfig(pessimistic_examples="negatives")
    z = np.zeros((8, 2), np.float32)
    m = np.ones(8, bool)
    with pytest.raises(ValueError, match="pos_mask"):
        ini.fit_initiation(z, m[:3], z, m)
    with pytest.raises(ValueError, match="feature"):
        ini.fit_initiation(z, m, np.zeros((8, 3), np.float32), m)
    with pytest.raises(ValueError, match="dirty"):
        ini.fit_initiation_batch(z[None], m[None], z[None], m[None], dirty=np.ones(2, bool))
