"""Maze layouts, bad-input errors, diverse starts, goal helpers and the point-mass twin (fast)."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from dscpp_jax import envs
from dscpp_jax.envs.maze_layout import get_layout, parse_map

TABLE = {  # name: (cell size, start, goal, number of merged wall boxes)
    "u_maze": (4.0, (0, 0), (0, 8), 5),
    "medium": (4.0, (0, 0), (20, 20), 13),
    "large": (4.0, (0, 0), (32, 24), 17),
    "four_rooms": (3.0, (0, 0), (12, 12), None),
    "ant_reacher": (3.0, (9, 9), (0, 0), 4),
}


def brute_in_wall(layout, xy):
    """NumPy oracle: the cell containing xy is a wall (or off the map)."""
    wall = layout.wall_grid()
    out = []
    for x, y in np.asarray(xy).reshape(-1, 2):
        j = int(np.floor(x / layout.cell_size + 0.5)) + layout.origin[1]
        i = int(np.floor(y / layout.cell_size + 0.5)) + layout.origin[0]
        out.append(not (0 <= i < wall.shape[0] and 0 <= j < wall.shape[1]) or bool(wall[i, j]))
    return np.array(out)


@pytest.mark.parametrize("name", list(TABLE))
def test_layout_table(name):
    size, start, goal, nboxes = TABLE[name]
    L = get_layout(name)
    assert L.cell_size == size
    np.testing.assert_allclose(L.start_xy, start)
    np.testing.assert_allclose(L.goal_xy, goal)
    if nboxes is not None:
        assert len(L.wall_boxes) == nboxes
    for robot in ("ant", "point"):
        # Envs expose the same coordinates (constructing the ant is cheap; nothing is compiled).
        env = envs.make(name, robot=robot)
        np.testing.assert_allclose(env.start, start)
        np.testing.assert_allclose(env.goal, goal)
        assert env.goal_size == 2 and env.episode_length == 1000 and env.goal_tolerance == 0.6
    # Merged boxes cover exactly the wall cells: compare with the cell grid on random points.
    xmin, xmax, ymin, ymax = L.bounds
    pts = np.random.default_rng(0).uniform([xmin - 1, ymin - 1], [xmax + 1, ymax + 1], (4000, 2))
    np.testing.assert_array_equal(np.asarray(L.in_wall(jnp.asarray(pts))), brute_in_wall(L, pts))


def test_four_rooms_doorways_and_reacher_arena():
    L = get_layout("four_rooms")
    doors = jnp.array([[6.0, 0.0], [0.0, 6.0], [12.0, 6.0], [6.0, 12.0]])
    assert not np.any(np.asarray(L.in_wall(doors)))
    R = get_layout("ant_reacher")
    np.testing.assert_allclose(R.bounds, (-13.5, 13.5, -13.5, 13.5))
    inside = jnp.array([[10.4, 10.4], [-10.4, -10.4], [-9.0, 9.0]])
    assert not np.any(np.asarray(R.in_wall(inside)))
    assert np.all(np.asarray(R.in_wall(jnp.array([[10.6, 0.0], [0.0, -10.6]]))))


def test_make_names_and_aliases():
    assert envs.make("point_u_maze").observation_size == 4
    assert envs.make("u_maze", robot="point").action_size == 2
    ant = envs.make("u_maze")
    assert ant.observation_size == 29 and ant.action_size == 8
    with pytest.raises(ValueError, match="unknown env name 'nope'.*u_maze"):
        envs.make("nope")
    with pytest.raises(ValueError, match="unknown robot"):
        envs.make("u_maze", robot="car")
    with pytest.raises(ValueError, match="unknown override"):
        envs.make("point_u_maze", nonsense=1)


BAD_MAPS = [
    ("111\n1r1\n1g\n111", "ragged rows"),
    ("1111\n1rx1\n1g01\n1111", "unknown character 'x'"),
    ("1111\n1001\n1g01\n1111", "no start"),
    ("1111\n1rr1\n1g01\n1111", "several starts"),
    ("1111\n1r01\n1001\n1111", "no goal"),
    ("11111\n1r101\n11101\n10g01\n11111", "cannot be reached"),
    ("", "empty"),
]


@pytest.mark.parametrize("text,msg", BAD_MAPS)
def test_bad_maps_raise_clear_errors(text, msg):
    with pytest.raises(ValueError, match=msg):
        envs.make_from_map(text, 2.0, robot="point")


def test_bad_start_goal_and_cell_size():
    good = "11111\n1r001\n10001\n100g1\n11111"
    with pytest.raises(ValueError, match="start .* inside a wall"):
        envs.make_from_map(good, 2.0, robot="point", start_xy=(-2.0, 0.0))
    with pytest.raises(ValueError, match="goal .* inside a wall"):
        envs.make("point_u_maze", goal_xy=(4.0, 4.0))
    with pytest.raises(ValueError, match="cell_size"):
        envs.make_from_map(good, -1.0)
    with pytest.raises(ValueError, match="unknown robot"):
        envs.make_from_map(good, 2.0, robot="car")


def test_custom_map_padding_and_coordinates():
    env = envs.make_from_map("r0\n0g", 2.0, robot="point", name="tiny")  # border padded with walls
    L = env.layout
    np.testing.assert_allclose(L.start_xy, (0, 0))
    np.testing.assert_allclose(L.goal_xy, (2, 2))
    assert L.rows[0] == "1111" and bool(L.in_wall(jnp.array([-1.5, 0.0])))
    env2 = envs.make("point_u_maze", goal_xy=(4.0, 8.0))
    np.testing.assert_allclose(env2.goal, (4, 8))


def test_goal_helpers_batched():
    obs = jnp.array([[0.0, 7.5, 1, 1], [0.0, 7.3, 0, 0], [3.0, 3.0, 0, 0]])
    goal = jnp.array([0.0, 8.0])
    np.testing.assert_allclose(envs.achieved_goal(obs), obs[:, :2])
    np.testing.assert_array_equal(envs.goal_reached(envs.achieved_goal(obs), goal), [True, False, False])
    np.testing.assert_array_equal(envs.goal_reward(envs.achieved_goal(obs), goal), [0.0, -1.0, -1.0])


@pytest.mark.parametrize("name", ["u_maze", "four_rooms", "ant_reacher", "large"])
def test_diverse_starts_avoid_walls_and_goal(name):
    env = envs.make(name, robot="point")
    xy = np.asarray(jax.jit(jax.vmap(env.sample_start))(jax.random.split(jax.random.key(0), 2000)))
    L = env.layout
    margin = env.config.start_margin
    # No start within `margin` of a wall: all 9 offsets of the margin square are free (NumPy oracle).
    for dx in (-margin * 0.999, 0, margin * 0.999):
        for dy in (-margin * 0.999, 0, margin * 0.999):
            assert not brute_in_wall(L, xy + np.array([dx, dy])).any()
    assert np.all(np.linalg.norm(xy - np.asarray(L.goal_xy), axis=1) > env.goal_tolerance)
    # Covers free space: starts land in most free cells.
    cells = {tuple(c) for c in np.round(xy / L.cell_size).astype(int)}
    assert len(cells) >= 0.9 * len(L.free_cells)
    if name == "ant_reacher":  # roughly uniform over [-10, 10]^2
        assert xy.min() < -9.5 and xy.max() > 9.5


def _point_rollout(env, key, actions, xy=None):
    s = env.reset(key) if xy is None else env.reset_at(key, xy)

    def f(s, a):
        s = env.step(s, a)
        return s, (s.obs, s.reward, s.done, s.info["success"])
    return jax.lax.scan(f, s, actions)


def test_point_walls_hold_and_speed():
    env = envs.make("point_four_rooms")
    T, B = 300, 64
    keys = jax.random.split(jax.random.key(1), B)
    acts = jax.random.uniform(jax.random.key(2), (B, T, 2), minval=-1, maxval=1)
    acts = acts.at[: B // 2].set(jnp.sign(acts[: B // 2, :1]))  # half of them push one way always
    starts = jax.vmap(env.sample_start)(keys)
    roll = jax.jit(jax.vmap(lambda k, a, xy: _point_rollout(env, k, a, xy)))
    _, (obs, _, _, _) = roll(keys, acts, starts)
    xy = np.asarray(obs[..., :2]).reshape(-1, 2)
    assert not brute_in_wall(env.layout, xy).any()
    assert not np.asarray(env.layout.in_wall(jnp.asarray(xy), 0.99 * env.config.radius)).any()
    # Crossing one 4.0 cell at full throttle from rest takes 10-20 steps.
    u = envs.make("point_u_maze")
    _, (obs, _, _, _) = jax.jit(lambda k: _point_rollout(u, k, jnp.tile(jnp.array([1.0, 0.0]), (40, 1)),
                                                         jnp.zeros(2)))(jax.random.key(0))
    n = int(np.argmax(np.asarray(obs[:, 0]) >= 4.0)) + 1
    assert 10 <= n <= 20, n


def test_point_reward_done_truncation_and_goal_override():
    env = envs.make("point_u_maze", episode_length=30)
    s = env.reset_at(jax.random.key(0), jnp.array([0.0, 7.0]))
    s = s.replace(info=dict(s.info, goal=jnp.array([0.0, 6.9])))  # caller-chosen subgoal
    s1 = env.step(s, jnp.zeros(2))
    assert float(s1.reward) == 0.0 and float(s1.done) == 1.0 and float(s1.info["success"]) == 1.0
    s = env.reset(jax.random.key(0))
    _, (obs, rew, done, succ) = jax.jit(lambda k: _point_rollout(env, k, jnp.zeros((30, 2))))(jax.random.key(0))
    assert np.all(np.asarray(rew) == -1.0)
    np.testing.assert_array_equal(np.asarray(done), [0.0] * 29 + [1.0])
    # Same key, same trajectory; different key, different start noise.
    a = jax.random.uniform(jax.random.key(5), (30, 2), minval=-1, maxval=1)
    r = jax.jit(lambda k: _point_rollout(env, k, a)[1][0])
    np.testing.assert_array_equal(np.asarray(r(jax.random.key(3))), np.asarray(r(jax.random.key(3))))
    assert not np.array_equal(np.asarray(r(jax.random.key(3))), np.asarray(r(jax.random.key(4))))
