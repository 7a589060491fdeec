"""The run configuration: every preset entry loads and validates, the table gives the Config the
presets always gave (tests/data/presets_golden.json), and bad fields are refused by name."""
from __future__ import annotations

import ast
import dataclasses
import json
import pathlib

import numpy as np
import pytest

from dscpp_jax import config as C
from dscpp_jax.config import (ALGOS, ENV_NAMES, FRONTIER_TABLE, PRESET_TABLE, PRESETS, SUBGOALS,
                              Config, parse_value, preset)

GOLDEN = pathlib.Path(__file__).parent / "data" / "presets_golden.json"


def _golden_config(golden: dict, key: str) -> dict:
    """The Config fields the golden file records for `key` ("preset/env/algo[/diverse_starts=
    false]"): the defaults, the variant's differences from them, and env, algo and preset; fields
    retired since (C.RETIRED_FIELDS) left out."""
    name, env, algo = key.split("/")[:3]
    out = {**golden["defaults"], **golden["variants"][golden["presets"][key]],
           "env": env, "algo": algo, "preset": name}
    return {k: v for k, v in out.items() if k not in C.RETIRED_FIELDS}


# Preset entries changed on purpose since the golden file was written: the paper's baselines
# (dsc, dual) lost what they had beyond the paper, the chain's frontier, the medium maze's
# model-free TD3 and the action penalty. (preset, env, algo) -> the fields' new values with
# diverse starts; with diverse_starts=false the frontier was off already, and only the other
# fields change.
L2_OFF = dict(td3_action_l2=0.0)
FRONTIER_OFF = dict(frontier_start_prob=0.0, frontier_parent=False, frontier_radius=5.0,
                    frontier_inner_radius=0.0)
MEDIUM_OFF = dict(L2_OFF, her_strategy="final", her_relabel_prob=0.5)
INTENDED = {
    ("fast", "u_maze", "dsc"): L2_OFF,
    ("fast", "u_maze", "dual"): L2_OFF,
    ("fast", "ant_reacher", "dsc"): L2_OFF,
    ("fast", "ant_reacher", "dual"): L2_OFF,
    ("fast", "four_rooms", "dsc"): dict(L2_OFF, **FRONTIER_OFF),
    ("fast", "four_rooms", "dual"): L2_OFF,
    ("fast", "large", "dsc"): dict(L2_OFF, **FRONTIER_OFF),
    ("fast", "large", "dual"): dict(L2_OFF, **FRONTIER_OFF),
    ("fast", "medium", "dsc"): dict(MEDIUM_OFF, **FRONTIER_OFF, max_options=24),
    ("fast", "medium", "dual"): dict(MEDIUM_OFF, **FRONTIER_OFF, max_options=24),
}
FRONTIER_ONLY = set(FRONTIER_OFF) | {"max_options"}


def _intended(key: str) -> dict:
    """The fields of golden entry `key` changed on purpose (INTENDED)."""
    name, env, algo = key.split("/")[:3]
    new = INTENDED.get((name, env, algo), {})
    if key.endswith("/diverse_starts=false"):
        new = {k: v for k, v in new.items() if k not in FRONTIER_ONLY}
    return new


def test_every_preset_gives_the_golden_config():
    golden = json.loads(GOLDEN.read_text())
    for key in golden["presets"]:              # each intended change is a change
        old = _golden_config(golden, key)
        assert all(old[k] != v for k, v in _intended(key).items()), key
    assert all("/".join(e) in golden["presets"] for e in INTENDED)
    fields = set(golden["defaults"]) - set(C.RETIRED_FIELDS)   # fields added since: defaults
    assert _only(golden["defaults"], fields) == _only(Config().flat(), fields)  # none changed
    keys = set(golden["presets"])
    assert len(keys) == len(PRESETS) * len(ENV_NAMES) * len(ALGOS) * 2
    for name in PRESETS:
        for env in ENV_NAMES:
            for algo in ALGOS:
                base = f"{name}/{env}/{algo}"
                for extra, key in (({}, base), ({"diverse_starts": True}, base),
                                   ({"diverse_starts": False}, base + "/diverse_starts=false")):
                    want = {**_golden_config(golden, key), **_intended(key), **extra}
                    for sub in (None,) + SUBGOALS:
                        kw = dict(extra) if sub is None else {**extra, "subgoal": sub}
                        got = preset(name, env, algo, **kw).flat()
                        assert _only(got, fields) == {**want, **kw}, (key, kw)
                        assert all(got[f] == Config().flat()[f] for f in set(got) - fields)
    assert _only(preset().flat(), fields) == _golden_config(golden, "fast/point_u_maze/mb_dscpp")


def _only(d: dict, keys) -> dict:
    return {k: v for k, v in d.items() if k in keys}


def _selectors():
    envs_ = {"*", *C.ENV_FAMILIES, *ENV_NAMES}
    learners = {"*", *C.LEARNER_CLASSES, *ALGOS}
    return envs_, learners


def _applied(name: str, env: str, algo: str) -> list:
    """The table entries preset(name, env, algo) applies, in order."""
    out = [e for _, e in C.matching_entries(PRESET_TABLE[name], env, algo)]
    if C.frontier_chain(name, env, algo):
        out += [e for _, e in C.matching_entries(FRONTIER_TABLE[name], env, algo)]
    return out


def test_every_preset_entry_loads_and_validates():
    env_sels, learner_sels = _selectors()
    assert set(PRESET_TABLE) == set(PRESETS) and set(FRONTIER_TABLE) <= set(PRESETS)
    for name in PRESETS:                                    # every merged preset validates
        for env in ENV_NAMES:
            for algo in ALGOS:
                cfg = preset(name, env, algo)
                assert isinstance(cfg, Config)
                cfg.validate()
    for table_name, table in (("PRESET_TABLE", PRESET_TABLE), ("FRONTIER_TABLE", FRONTIER_TABLE)):
        for name, entries in table.items():
            for key, entry in entries.items():
                where = f"{table_name}[{name!r}][{key!r}]"
                assert key[0] in env_sels and key[1] in learner_sels, where
                assert entry and set(entry) <= set(C.FLAT_NAMES), where
                Config().override(**entry)                  # each value fits its field
                hits = [(e, a) for e in ENV_NAMES for a in ALGOS
                        if any(e_ is entry for e_ in _applied(name, e, a))]
                assert hits, f"{where} applies to no environment and learner"
                for env, algo in hits:                      # its values reach the Config unless a
                    cfg = preset(name, env, algo)           # later entry sets the same field
                    for k in entry:
                        last = [e for e in _applied(name, env, algo) if k in e][-1]
                        assert cfg.get(k) == last[k], (where, env, algo, k)


def test_presets_merge_from_the_least_to_the_most_specific_entry():
    keys = [k for k, _ in C.matching_entries(PRESET_TABLE["fast"], "medium", "mf_dscpp")]
    assert keys == [("ant", "*"), ("ant", "model_free"), ("medium", "mf_dscpp")]
    keys = [k for k, _ in C.matching_entries(FRONTIER_TABLE["fast"], "medium", "mb_dscpp")]
    assert keys == [("*", "*"), ("medium", "*"), ("medium", "mb_dscpp")]
    assert C.matching_entries(PRESET_TABLE["paper"], "point_medium", "dsc") == [
        (("*", "*"), PRESET_TABLE["paper"]["*", "*"])]
    f = C.preset_fields("fast", "medium", "mb_dscpp")
    assert f["td3_updates_per_step"] == 1.0 and f["max_options"] == 32   # the frontier's, last
    assert C.preset_fields("fast", "medium", "mb_dscpp", diverse_starts=False)[
        "td3_updates_per_step"] == 0.25


def test_known_preset_values():
    p = preset("paper", "u_maze", "mb_dscpp")
    assert (p.mpc.samples, p.mpc.horizon, p.chain.gestation, p.run.num_envs, p.run.steps_per_iter,
            p.run.total_episodes, p.task.ant_integrator) == (14000, 7, 10, 1, 1000, 2001, "RK4")
    assert preset("paper", "point_u_maze", "mb_dscpp").task.ant_integrator == "Euler"
    pt = preset("fast", "point_medium", "mf_dscpp")
    assert (pt.run.num_envs, pt.mpc.samples, pt.chain.gestation, pt.chain.max_options, pt.td3.lr) == (
        16, 128, 5, 8, 3e-4)
    assert not pt.frontier_on                               # the point twins: the paper's rule
    assert preset("fast", "u_maze", "mb_dscpp").mpc.samples == 2048
    assert preset("fast", "large", "mb_dscpp").mpc.samples == 4096
    assert preset("fast", "four_rooms", "dual").chain.gestation == 10
    assert not preset("fast", "four_rooms", "dual").frontier_on
    mb, mf = preset("fast", "medium", "mb_dscpp"), preset("fast", "medium", "td3_her")
    assert mb.frontier_on and mb.chain.max_options == 32 and mb.td3.dtype == "float32"
    assert (mf.td3.dtype, mf.td3.batch_size) == ("bfloat16", 512) and not mf.frontier_on
    assert {k: mf.get(k) for k in C.MEDIUM_MODEL_FREE_TD3} == C.MEDIUM_MODEL_FREE_TD3
    off = preset("fast", "medium", "mf_dscpp", diverse_starts=False)
    assert not off.frontier_on and off.chain.max_options == 24
    assert not preset("paper", "medium", "mb_dscpp").frontier_on


def test_the_paper_baselines_get_nothing_beyond_the_paper():
    for name in PRESETS:
        for env in ENV_NAMES:
            for algo in C.PAPER_BASELINES:
                cfg = preset(name, env, algo)
                assert not cfg.frontier_on and cfg.td3.action_l2 == 0.0, (name, env, algo)
                assert (cfg.td3.her_strategy, cfg.td3.her_relabel_prob) == ("final", 0.5)
                assert C.paper_rule_overrides(name, env, algo) == {}
    assert all(not set(C.PAPER_BASELINES) & set(a) for a in C.FRONTIER_CHAINS.values())
    # DSC++ keeps its extras; paper_rule_overrides turns them off
    mb = C.paper_rule_overrides("fast", "medium", "mb_dscpp")
    assert mb == dict(max_options=24, frontier_start_prob=0.0, frontier_parent=False,
                      td3_updates_per_step=0.25)
    mf = preset("fast", "medium", "mf_dscpp", **C.paper_rule_overrides("fast", "medium",
                                                                        "mf_dscpp"))
    assert not mf.frontier_on and (mf.td3.her_strategy, mf.td3.her_relabel_prob, mf.td3.action_l2,
                                   mf.chain.max_options) == ("final", 0.5, 1.0, 24)
    assert C.paper_rule_overrides("fast", "four_rooms", "mf_dscpp") == dict(
        frontier_start_prob=0.0, frontier_parent=False)
    assert C.paper_rule_overrides("fast", "u_maze", "mb_dscpp") == {}
    assert C.paper_rule_overrides("paper", "medium", "mf_dscpp") == {}
    assert C.paper_rule_overrides("fast", "point_medium", "mf_dscpp") == {}


def test_env_names_are_those_envs_make_builds():
    from dscpp_jax import envs
    assert ENV_NAMES == tuple(envs.ENV_NAMES)


def test_every_field_has_a_docstring():
    tree = ast.parse(pathlib.Path(C.__file__).read_text())
    for cls_ in (Config, *C.SECTIONS.values()):
        cls = next(n for n in tree.body if isinstance(n, ast.ClassDef) and n.name == cls_.__name__)
        documented = set()
        for a, b in zip(cls.body, cls.body[1:]):
            if (isinstance(a, ast.AnnAssign) and isinstance(b, ast.Expr)
                    and isinstance(b.value, ast.Constant) and isinstance(b.value.value, str)):
                documented.add(a.target.id)
        assert documented == {f.name for f in dataclasses.fields(cls_)}, cls_.__name__


def test_field_types_are_checked_naming_the_field_value_and_type():
    with pytest.raises(ValueError, match=r"gestation='abc' \(str\); gestation is an integer"):
        Config().override(gestation="abc")
    with pytest.raises(ValueError, match=r"gestation=2\.5 .*an integer"):
        Config(gestation=2.5)
    with pytest.raises(ValueError, match="gestation=True"):
        Config(gestation=True)                              # a bool is no integer here
    for bad in (1, "true", None):
        with pytest.raises(ValueError, match="diverse_starts.*true or false"):
            Config().override(diverse_starts=bad)
    with pytest.raises(ValueError, match="td3_lr='fast'.*a number"):
        Config(td3_lr="fast")
    with pytest.raises(ValueError, match="env=3 .*a string"):
        Config(env=3)
    assert Config(td3_lr=1).td3.lr == 1 and Config(td3_lr=1) == Config(td3_lr=1.0)
    assert Config(seed=np.int64(3)).run.seed == 3               # NumPy integers are integers
    with pytest.raises(ValueError, match="gestation='abc'"):
        preset("fast", "point_u_maze", "mb_dscpp", gestation="abc")
    # a section built directly names its fields as section.field, the name it was given
    with pytest.raises(ValueError, match=r"td3\.batch_size='x' \(str\); td3\.batch_size is an"):
        C.TD3Section(batch_size="x")


def test_value_errors_name_fields_a_user_can_type():
    """Messages that concern a sectioned field give a name `--set` takes (flat) and, where two
    sections have a field of that name, its section.field name too."""
    for kw, says in (
            (dict(td3_updates_per_step=-1.0), "td3_updates_per_step=-1.0 (td3.updates_per_step)"),
            (dict(dyn_updates_per_step=-1.0),
             "dyn_updates_per_step=-1.0 (dynamics.updates_per_step) must be >= 0"),
            (dict(discount=0.0), "discount=0.0 (td3.discount) must be in (0, 1]"),
            (dict(mpc_discount=1.5), "mpc_discount=1.5 (mpc.discount) must be in (0, 1]")):
        with pytest.raises(ValueError) as e:
            Config(**kw).validate()
        assert says in str(e.value), str(e.value)
        name = says.split("=", 1)[0]
        assert name in C.FLAT_NAMES and C.DOTTED_NAMES[name] in says


@pytest.mark.parametrize("name", sorted(C.CHOICES))
def test_fields_with_fixed_values_refuse_others_listing_them(name):
    allowed = C.CHOICES[name]
    with pytest.raises(ValueError) as e:
        Config().override(**{name: "nope"})
    assert f"{name}='nope'" in str(e.value) and all(str(a) in str(e.value) for a in allowed)
    with pytest.raises(ValueError, match=f"{name}='nope'"):
        dataclasses.replace(Config(), **{name: "nope"}).validate()
    if name != "algo":                                      # (preset's own argument)
        with pytest.raises(ValueError, match=f"{name}='nope'"):
            preset("fast", "point_u_maze", "mb_dscpp", **{name: "nope"}).validate()
    for value in allowed:
        Config().override(**{name: value})


def test_a_saved_run_with_a_dropped_value_loads_but_does_not_validate():
    saved = {**Config().to_dict(), "subgoal": "nearest"}
    cfg = Config.from_saved(saved)
    assert cfg.subgoal == "nearest"
    with pytest.raises(ValueError, match="subgoal='nearest'; subgoal must be robust or dp"):
        cfg.validate()
    with pytest.raises(ValueError, match="this run: .*gestation='x'"):
        Config.from_saved({**saved, "gestation": "x"})


def test_preset_refuses_unknown_presets_environments_learners_and_fields():
    with pytest.raises(ValueError, match="unknown preset 'quick'.*paper.*fast"):
        preset("quick")
    with pytest.raises(ValueError,
                       match="unknown env name 'no_such_maze'.*valid names.*point_u_maze"):
        preset("fast", "no_such_maze")
    with pytest.raises(ValueError, match="unknown learner algo='nope'.*mb_dscpp.*td3_her"):
        preset(algo="nope")
    with pytest.raises(ValueError, match=r"unknown config field\(s\) \['gestatoin'\]"):
        preset(gestatoin=3)
    with pytest.raises(ValueError, match=r"unknown config field\(s\) \['gestatoin'\]"):
        Config().override(gestatoin=3)


def test_parse_value_converts_to_the_field_type_and_names_the_field():
    assert parse_value("gestation", "7") == 7 and parse_value("gestation", "1e3") == 1000
    assert parse_value("td3_lr", "3e-4") == 3e-4 and parse_value("td3_lr", "1") == 1.0
    assert parse_value("diverse_starts", "off") is False and parse_value("td3_clip_targets", "yes")
    assert parse_value("her_strategy", "future") == "future"
    assert parse_value("env", "point_medium") == "point_medium"
    for field_name, text, says in (("gestation", "abc", "gestation is an integer"),
                                   ("gestation", "2.5", "gestation is an integer"),
                                   ("gestation", "1e999", "gestation is an integer"),
                                   ("td3_lr", "fast", "td3_lr is a number"),
                                   ("diverse_starts", "maybe", "diverse_starts is true or false")):
        with pytest.raises(ValueError, match=f"--set {field_name}='{text}': {says}.*e.g. --set "
                                             f"{field_name}="):
            parse_value(field_name, text)
    with pytest.raises(ValueError, match="unknown config field 'gestatoin'"):
        parse_value("gestatoin", "3")


def test_config_module_keeps_no_results_or_dates():
    text = pathlib.Path(C.__file__).read_text()
    for pattern in ("+-", "±", "seeds each", "round)", "2026"):
        assert pattern not in text, pattern
