"""Stream NBV keyframe policies on a tiny ray-cast box room: one keyframe per window, scorer agreement."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest

from roigsf_ros.core.camera import Intrinsics
from roigsf_ros.core.errors import InputError
from roigsf_ros.core.frame import Frame
from roigsf_ros.data.scene import MeshRenderer, look_at
from roigsf_ros.mapping.mapper import Mapper, MapperConfig
from roigsf_ros.nbv.scorer import NBVScorer
from roigsf_ros.policies.base import make_policy, policy_names
from roigsf_ros.policies.stream import STREAM_POLICIES, StreamNBVPolicy

INTR = Intrinsics(width=48, height=36, fx=40.0, fy=40.0, cx=23.5, cy=17.5)
UP = np.array([0.0, 0.0, 1.0])
WINDOW = 4
N_FRAMES = 12


pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture(scope="module")
def frames() -> list[Frame]:
    """12 frames panning around a 4 x 3 x 2.5 m box room with a cube on the floor."""
    room = o3d.geometry.TriangleMesh.create_box(4.0, 3.0, 2.5).translate((-2.0, -1.5, 0.0))
    cube = o3d.geometry.TriangleMesh.create_box(0.6, 0.6, 0.6).translate((0.8, -0.3, 0.0))
    renderer = MeshRenderer(room + cube, texture_seed=1)
    out = []
    for i, a in enumerate(np.linspace(-0.6, 1.6, N_FRAMES)):
        eye = np.array([-0.5, -0.3, 1.3]) + 0.15 * np.array([np.cos(a), np.sin(a), 0.0])
        T = look_at(eye, eye + np.array([np.cos(a), np.sin(a), -0.3]), UP)
        rgb, depth = renderer.render(T, INTR)
        out.append(Frame(index=100 + i, rgb=rgb, depth_m=depth, T_wc=T))
    return out


def mapper_config() -> MapperConfig:
    return MapperConfig(iters_per_keyframe=3, seed=1, densify_stride=2, mesh_voxel_size_m=0.05, mesh_sdf_trunc_m=0.15)


def run_stream(policy: StreamNBVPolicy, frames: list[Frame], check=None) -> Mapper:
    """What run_offline does per frame: observe, insert what it names; ``check(policy, mapper, k)`` before each."""
    mapper = Mapper(INTR, mapper_config())
    policy.reset()
    for k, frame in enumerate(frames):
        if check is not None:
            check(policy, mapper, k)
        for keyframe in policy.observe(frame, mapper):
            mapper.add_keyframe(keyframe)
    for keyframe in policy.finish(mapper):
        mapper.add_keyframe(keyframe)
    return mapper


def test_registry_and_params() -> None:
    assert set(STREAM_POLICIES) <= set(policy_names())
    pol = make_policy("roi-gsurfisher", window=5, seed=None, epsilon=0.5)
    assert isinstance(pol, StreamNBVPolicy) and pol.mode == "roi-gsurfisher" and pol.name == "roi-gsurfisher"
    assert pol.window == 5 and pol.trigger_every == 5 and pol.config.epsilon == 0.5
    assert pol.params()["window"] == 5 and pol.params()["epsilon"] == 0.5
    assert make_policy("random").mode is None and make_policy("fisherrf").config.mode == "fisherrf"
    with pytest.raises(InputError):
        make_policy("close-front", window=0)
    with pytest.raises(InputError):
        make_policy("close-front", trigger_every=-1)
    with pytest.raises(InputError, match="takes no parameter"):
        make_policy("roi-fisher", mode="fisherrf")


@pytest.mark.parametrize("name", STREAM_POLICIES)
def test_one_keyframe_per_window(name: str, frames: list[Frame]) -> None:
    policy = make_policy(name, window=WINDOW, seed=3)
    mapper = run_stream(policy, frames)
    n_windows = (N_FRAMES - 1) // WINDOW
    assert mapper.keyframe_ids[0] == frames[0].index  # the first frame is always a keyframe
    assert len(mapper.keyframe_ids) == 1 + n_windows
    assert mapper.keyframe_ids[1:] == policy.inserted_ids and policy.triggers == n_windows
    for w, kf_id in enumerate(policy.inserted_ids):  # each winner comes from its own window
        lo = frames[1 + w * WINDOW].index
        assert lo <= kf_id < lo + WINDOW
    assert len(set(mapper.keyframe_ids)) == len(mapper.keyframe_ids)
    if policy.needs_tsdf:
        assert policy.tsdf is not None and policy.tsdf.n_integrated == len(mapper.keyframes)
    if policy.last_result is not None:
        r = policy.last_result
        for arr in (r.fused, r.fisher, r.close_front):
            assert np.all(np.isfinite(arr))
        assert len(r.fused) == WINDOW and len(policy.last_candidate_ids) == WINDOW
        if name in ("roi-gsurfisher", "roi-fisher", "fisherrf"):
            assert np.any(r.fisher > 0)
        if name in ("roi-gsurfisher", "close-front"):
            assert np.any(r.close_front > 0)


def test_random_is_deterministic_for_a_seed(frames: list[Frame]) -> None:
    picks = []
    for seed in (7, 7, 8, 9, 10):
        pol = make_policy("random", window=WINDOW, seed=seed)
        run_stream(pol, frames)
        picks.append(tuple(pol.inserted_ids))
    assert picks[0] == picks[1]
    assert len(set(picks[1:])) > 1  # other seeds pick differently (with overwhelming likelihood, fixed here)
    pol = make_policy("random", window=WINDOW, seed=7)
    run_stream(pol, frames)
    assert tuple(pol.inserted_ids) == picks[0]  # reset() re-seeds


def test_trigger_every_differs_from_window(frames: list[Frame]) -> None:
    pol = make_policy("close-front", window=3, trigger_every=2)
    mapper = run_stream(pol, frames)
    assert len(mapper.keyframe_ids) == 1 + (N_FRAMES - 1) // 2
    assert pol.last_candidate_ids and len(pol.last_candidate_ids) <= 3


def test_roi_gsurfisher_choice_matches_the_scorer(frames: list[Frame]) -> None:
    """With ``close_front_exact`` the kept state scores exactly as the scorer from scratch (W_f from every pose)."""
    policy = make_policy("roi-gsurfisher", window=WINDOW, close_front_exact=True)
    expected: list[tuple[int, np.ndarray]] = []

    def check(pol: StreamNBVPolicy, mapper: Mapper, k: int) -> None:
        if k == 0 or k % WINDOW != 0:
            return  # not a trigger frame: frames 1..4 -> trigger at k = 4, 8
        pol.sync_tsdf(mapper)
        window = frames[k - WINDOW + 1 : k + 1]
        r = NBVScorer().score(mapper.map, mapper.h_train, pol.tsdf, mapper.keyframe_poses,
                              [f.T_wc for f in window], INTR, mode="roi-gsurfisher")  # fmt: skip
        expected.append((window[r.best_index].index, r.fused))

    run_stream(policy, frames, check)
    assert len(expected) == 2
    assert [e[0] for e in expected] == policy.inserted_ids
    np.testing.assert_allclose(policy.last_result.fused, expected[-1][1], rtol=1e-9, atol=1e-12)
    incremental = make_policy("roi-gsurfisher", window=WINDOW)  # the default: each keyframe folded into W_f once
    run_stream(incremental, frames)
    assert incremental.inserted_ids == policy.inserted_ids
    assert incremental.state.close_front_builds == 1 and incremental.state.close_front_views_added >= 1


def test_policy_passes_any_nbv_config_field() -> None:
    """Every NBVConfig field is a policy parameter (the beyond-paper options included); unknown ones raise."""
    p = make_policy("roi-gsurfisher", window=4, beta=2.0)
    assert p.config.beta == 2.0 and p.params()["beta"] == 2.0
    with pytest.raises(InputError):
        make_policy("roi-gsurfisher", no_such_option=1.0)
    with pytest.raises(InputError):
        make_policy("roi-gsurfisher", mode="fisherrf")


def test_adaptive_trigger_inserts_only_high_gain_windows(frames: list[Frame], monkeypatch: pytest.MonkeyPatch) -> None:
    """Beyond the paper: trigger="adaptive" inserts a window's best only when its raw gain reaches the ratio x the
    median of the recent ones (or after max_gap empty triggers); "window" (default) inserts at every trigger."""
    from types import SimpleNamespace

    gains = iter([5.0, 4.0, 1.0, 9.0, 1.0, 1.0, 1.0, 1.0, 8.0, 1.0, 1.0])

    def fake_choose(self: StreamNBVPolicy, candidates: list[Frame], mapper: Mapper, ahead: object = None) -> int:
        self.last_result = SimpleNamespace(fisher=np.array([next(gains)]), close_front=np.zeros(1))
        return 0

    monkeypatch.setattr(StreamNBVPolicy, "choose", fake_choose)
    pol = make_policy("roi-fisher", window=2, trigger_every=1, trigger="adaptive", adaptive_max_gap=3)
    assert pol.params()["trigger"] == "adaptive"
    mapper = run_stream(pol, frames)  # 11 triggers, gains as above
    # medians of the history before each trigger: -, -, 4.5, 4, 4.5, 4, 2.5 (gap 2 -> forced), 1, 1, 1, 1
    accepted = [True, True, False, True, False, False, True, True, True, True, True]
    assert pol.triggers == 11 and pol.skipped_triggers == accepted.count(False)
    assert len(mapper.keyframe_ids) == 1 + sum(accepted) and len(pol.inserted_ids) == sum(accepted)
    with pytest.raises(InputError):
        make_policy("random", trigger="adaptive")
    with pytest.raises(InputError):
        make_policy("roi-fisher", trigger="sometimes")
    assert make_policy("roi-fisher").trigger == "window"


def test_budget_trigger_spends_a_fixed_keyframe_budget_on_high_gain_windows(
    frames: list[Frame], monkeypatch: pytest.MonkeyPatch
) -> None:
    """Beyond the paper: trigger="budget" earns 1 / budget_every keyframe per frame, scores only when a whole one
    is banked, inserts when the gain (here the unseen fraction) reaches the median of the recent ones or when the
    bank would overflow by the next trigger; never more than 1 + (F - 1) // budget_every keyframes."""
    from types import SimpleNamespace

    gains = iter([0.5, 0.4, 0.1, 0.9, 0.1, 0.2, 0.0, 0.8])

    def fake_choose(self: StreamNBVPolicy, candidates: list[Frame], mapper: Mapper, ahead: object = None) -> int:
        g = np.array([next(gains)])
        self.last_result = SimpleNamespace(fisher=np.ones(1), close_front=np.zeros(1), unseen=g)
        return 0

    monkeypatch.setattr(StreamNBVPolicy, "choose", fake_choose)
    pol = make_policy("roi-gsurfisher", window=3, trigger_every=1, trigger="budget", budget_every=2, budget_burst=2)
    assert pol.params()["trigger"] == "budget" and pol.params()["budget_every"] == 2.0
    mapper = run_stream(pol, frames)
    # frames 1..11 bank 0.5 each; scored at frames 2, 4, 6, 7, 8, 9, 10, 11 (a whole keyframe banked):
    # 0.5, 0.4 (first two: in), 0.1 < 0.45 out, 0.9 > 0.4 in, 0.1 < 0.45 out, 0.2 < 0.4 out, 0.0 forced (bank 2 + 0.5
    # would overflow 2) in, 0.8 > 0.2 in
    assert pol.triggers == 8 and pol.skipped_triggers == 3 + 3
    assert len(pol.inserted_ids) == 5 == (N_FRAMES - 1) // 2 and len(mapper.keyframe_ids) == 6
    assert pol.tokens == pytest.approx(0.5)
    with pytest.raises(InputError):
        make_policy("random", trigger="budget")
    with pytest.raises(InputError):  # a bank that cannot hold one keyframe plus a trigger's earnings
        make_policy("roi-fisher", window=4, trigger="budget", budget_every=4, budget_burst=1.5)
    with pytest.raises(InputError):  # more than one keyframe per trigger
        make_policy("roi-fisher", window=4, trigger_every=4, trigger="budget", budget_every=2)


def test_budget_trigger_with_the_real_scorer_keeps_its_budget(frames: list[Frame]) -> None:
    """The budget trigger on the real scorer with the unseen term: the count bound holds and the gain is U."""
    pol = make_policy("roi-gsurfisher", window=4, trigger_every=2, trigger="budget", budget_every=4, unseen_weight=1.0)
    mapper = run_stream(pol, frames)
    assert 2 <= len(mapper.keyframe_ids) <= 1 + (N_FRAMES - 1) // 4
    assert pol.last_result is not None and pol.last_result.unseen is not None
    pick = int(pol.last_result.best_index)
    assert pol.gain(pick) == pytest.approx(float(pol.last_result.unseen[pick]))


def reference_novelty(returned: list[Frame], cand: Frame, mapper: Mapper, voxel_m: float = 0.025) -> float:
    """Area (m^2) of the candidate's depth voxels farther than 5 cm + half a voxel from the returned frames' voxels."""
    from scipy.spatial import cKDTree

    from roigsf_ros.core.camera import depth_points_w

    def vox(f: Frame) -> np.ndarray:
        pts = depth_points_w(f.depth_m, f.T_wc, INTR, mapper.valid_depth_mask(f.depth_m))
        return np.unique(np.floor(pts / voxel_m).astype(np.int64), axis=0).astype(np.float64)

    q = vox(cand)
    dist, _ = cKDTree(np.concatenate([vox(f) for f in returned])).query(q, k=1)
    return float(np.count_nonzero(dist > (0.05 + 0.5 * voxel_m) / voxel_m + 1e-9)) * voxel_m**2


def test_novelty_policy_picks_the_frame_whose_depth_shows_the_most_new_surface(frames: list[Frame]) -> None:
    """Beyond the paper, stream only: N of each window frame against the depth of every frame returned before."""
    pol = make_policy("novelty", window=WINDOW)
    assert pol.params() == {"window": WINDOW, "trigger_every": WINDOW, "seed": 0, "novelty_voxel_m": 0.025,
                            "novelty_radius_m": 0.05}  # fmt: skip
    by_id = {f.index: f for f in frames}
    checked = []

    def check(policy: StreamNBVPolicy, mapper: Mapper, k: int) -> None:
        if policy.last_novelty is not None and policy.last_candidate_ids and len(checked) < policy.triggers:
            returned = [by_id[i] for i in mapper.keyframe_ids[:-1]]  # the keyframes before the last trigger's pick
            ref = [reference_novelty(returned, by_id[i], mapper) for i in policy.last_candidate_ids]
            np.testing.assert_allclose(policy.last_novelty, ref, rtol=0, atol=1e-12)
            assert mapper.keyframe_ids[-1] == policy.last_candidate_ids[int(np.argmax(ref))]
            checked.append(k)

    mapper = run_stream(pol, frames, check)
    assert len(checked) == (N_FRAMES - 1) // WINDOW  # every trigger, checked at the next frame
    assert pol.observed is not None and pol.observed.n_added == len(mapper.keyframe_ids)
    assert pol.last_result is None and pol.gain(0) == pytest.approx(float(pol.last_novelty[0]))


def test_lookahead_decides_each_window_one_trigger_late_by_the_pair_it_makes(frames: list[Frame]) -> None:
    """``lookahead``: a window's pick is judged by its new surface plus the most one newer frame adds after it."""
    pol = make_policy("novelty", window=WINDOW, lookahead=WINDOW)
    assert pol.params()["lookahead"] == WINDOW and pol.window == WINDOW and pol.trigger_every == WINDOW
    by_id = {f.index: f for f in frames}
    seen: list[tuple[list[int], list[int], np.ndarray]] = []

    def check(policy: StreamNBVPolicy, mapper: Mapper, k: int) -> None:
        if k == 1 + WINDOW:  # the first trigger: every frame held is still ahead, nothing decided
            assert len(mapper.keyframe_ids) == 1 and policy.triggers == 0
        if policy.triggers > len(seen):
            returned = [by_id[i] for i in mapper.keyframe_ids[:-1]]
            ref = [reference_novelty(returned, by_id[c], mapper)
                   + max(reference_novelty([*returned, by_id[c]], by_id[g], mapper) for g in policy.last_ahead_ids)
                   for c in policy.last_candidate_ids]  # fmt: skip
            np.testing.assert_allclose(policy.last_novelty, ref, rtol=0, atol=1e-12)
            assert mapper.keyframe_ids[-1] == policy.last_candidate_ids[int(np.argmax(ref))]
            seen.append((list(policy.last_candidate_ids), list(policy.last_ahead_ids), policy.last_novelty))

    mapper = run_stream(pol, frames, check)
    assert len(seen) == (N_FRAMES - 1) // WINDOW - 1  # every trigger but the first decided, each checked
    cands, ahead, _ = seen[0]
    assert cands == [f.index for f in frames[1 : 1 + WINDOW]] and ahead == [f.index for f in frames[1 + WINDOW : 9]]
    # finish() decided the frames still held, with nothing ahead: the same count as one keyframe per window
    assert len(mapper.keyframe_ids) == 1 + (N_FRAMES - 1) // WINDOW and pol.last_ahead_ids == []
    assert pol.finish(mapper) == []  # once
    assert make_policy("novelty", window=WINDOW).finish(mapper) == []  # nothing held back without lookahead
    assert make_policy("roi-gsurfisher", window=WINDOW, novelty_weight=1.0, lookahead=2).params()["lookahead"] == 2
    for name, params in [("roi-fisher", {"lookahead": 4}), ("random", {"lookahead": 4}),
                         ("novelty", {"lookahead": -1}), ("novelty", {"lookahead": 1.5}),
                         ("novelty", {"lookahead": 4, "trigger": "adaptive"})]:  # fmt: skip
        with pytest.raises(InputError, match="lookahead"):
            make_policy(name, **params)


def test_novelty_measure_pixels_ranks_by_the_held_frames_pixels_each_pick_covers(frames: list[Frame]) -> None:
    """``novelty_measure=pixels``: each trigger's novelty is ObservedSurface.held_pixels_covered of the window's frames
    against the keyframes returned before, and the pick is its best."""
    from roigsf_ros.core.camera import depth_points_w
    from roigsf_ros.nbv.novelty import ObservedSurface

    pol = make_policy("novelty", window=WINDOW, lookahead=WINDOW, novelty_measure="pixels")
    assert pol.params()["novelty_measure"] == "pixels" and "novelty_measure" not in make_policy("novelty").params()
    by_id = {f.index: f for f in frames}
    checked: list[int] = []

    def check(policy: StreamNBVPolicy, mapper: Mapper, k: int) -> None:
        if policy.triggers > len(checked):

            def points(i: int) -> np.ndarray:
                f = by_id[i]
                return depth_points_w(f.depth_m, f.T_wc, INTR, mapper.valid_depth_mask(f.depth_m))

            ref = ObservedSurface(measure="pixels")
            for i in mapper.keyframe_ids[:-1]:  # the keyframes before the last trigger's pick
                ref.add_points(points(i))
            want = ref.held_pixels_covered([points(i) for i in policy.last_candidate_ids],
                                           [points(i) for i in policy.last_ahead_ids])  # fmt: skip
            np.testing.assert_array_equal(policy.last_novelty, want)
            assert mapper.keyframe_ids[-1] == policy.last_candidate_ids[int(np.argmax(want))]
            checked.append(k)

    mapper = run_stream(pol, frames, check)
    assert len(checked) == (N_FRAMES - 1) // WINDOW - 1 and len(mapper.keyframe_ids) == 1 + (N_FRAMES - 1) // WINDOW
    for name, params in [("novelty", {"novelty_measure": "volume"}), ("roi-fisher", {"novelty_measure": "pixels"}),
                         ("random", {"novelty_measure": "pixels"})]:  # fmt: skip
        with pytest.raises(InputError, match="novelty_measure"):  # unknown, or no novelty to count
            make_policy(name, **params)
    assert (
        make_policy("roi-fisher", novelty_weight=1.0, novelty_measure="pixels").params()["novelty_measure"] == "pixels"
    )


def test_novelty_weight_adds_its_z_score_to_the_fused_score(frames: list[Frame]) -> None:
    from roigsf_ros.nbv.scorer import zscore

    pol = make_policy("roi-gsurfisher", window=WINDOW, unseen_weight=1.0, novelty_weight=1.0)
    assert pol.params()["novelty_weight"] == 1.0
    mapper = run_stream(pol, frames)
    r, n = pol.last_result, pol.last_novelty
    assert r is not None and n is not None and np.ptp(n) > 0
    assert mapper.keyframe_ids[-1] == pol.last_candidate_ids[int(np.argmax(r.fused + zscore(n)))]
    heavy = make_policy("roi-gsurfisher", window=WINDOW, novelty_weight=1e9)  # N decides: the novelty policy's picks
    assert (
        run_stream(heavy, frames).keyframe_ids == run_stream(make_policy("novelty", window=WINDOW), frames).keyframe_ids
    )
    budget = make_policy("roi-fisher", window=4, trigger_every=2, trigger="budget", budget_every=4, unseen_weight=1.0,
                         novelty_weight=0.5)  # fmt: skip
    run_stream(budget, frames)
    assert budget.gain(1) == pytest.approx(float(budget.last_novelty[1]))  # the budget's gain is N, not U
    for name, params, field in [("random", {"novelty_weight": 1.0}, "novelty_weight"),
                                ("novelty", {"novelty_weight": 1.0}, "novelty_weight"),
                                ("roi-fisher", {"novelty_weight": -1.0}, "novelty_weight"),
                                ("novelty", {"novelty_voxel_m": 0.0}, "novelty_voxel_m")]:  # fmt: skip
        with pytest.raises(InputError, match=field):
            make_policy(name, **params)
    no_depth = Frame(index=1, rgb=np.zeros((0, 0, 3), np.uint8), depth_m=np.zeros((0, 0), np.float32),
                     T_wc=frames[0].T_wc)  # fmt: skip
    with pytest.raises(InputError, match=r"frame 1 depth_m.*pool"):
        make_policy("novelty").choose([no_depth], Mapper(INTR, mapper_config()))


def test_make_policy_errors_name_the_policy_not_a_command_line_flag() -> None:
    """The library is called by the CLI, a node parameter and a pool config alike: its errors name no `--policy`."""
    with pytest.raises(InputError, match=r"^policy 'nosuch': unknown keyframe policy; choose one of .*gaus-slam"):
        make_policy("nosuch")
    with pytest.raises(InputError, match=r"^policy 'gaus-slam': takes no parameter\(s\) n$"):
        make_policy("gaus-slam", n=3)


def test_every_n_spec_takes_the_node_parameter_name_and_keeps_n_as_an_alias() -> None:
    """``every-n:every_n=10`` (the node parameter's name, as ``roigsf map --every-n``) was refused with "takes no
    parameter(s) every_n"; ``every-n:n=10`` (older specs and results) still parses; the name typed is the one named."""
    from roigsf_ros.experiments.bench import parse_policies

    specs = parse_policies("every-n:every_n=10,every-n:n=4", "stream")
    assert [make_policy(s.name, **s.params).n for s in specs] == [10, 4]
    assert make_policy("every-n", every_n=3).params() == {"every_n": 3} and make_policy("every-n").n == 5
    with pytest.raises(InputError, match=r"^every_n: must be at least 1, got 0$"):
        make_policy("every-n", every_n=0)
    with pytest.raises(InputError, match=r"^n: must be at least 1, got 0$"):  # callers rename the alias (--every-n)
        make_policy("every-n", n=0)
    with pytest.raises(InputError, match=r"^every_n: given twice"):
        make_policy("every-n", every_n=3, n=4)


def test_a_misspelt_policy_parameter_gets_the_closest_name() -> None:
    """As the nodes do for an undeclared parameter: ``unseen_wieght`` had no hint; names nothing close stay bare."""
    from roigsf_ros.experiments.bench import parse_policies

    with pytest.raises(InputError, match=r"takes no parameter\(s\) unseen_wieght \(did you mean 'unseen_weight'\?\)$"):
        parse_policies("roi-gsurfisher:unseen_wieght=2", "stream")
    hint = r"^policy 'roi-gsurfisher': takes no parameter\(s\) windw \(did you mean 'window'\?\), zzz$"
    with pytest.raises(InputError, match=hint):  # a stream policy's own option, not an NBVConfig field
        make_policy("roi-gsurfisher", windw=3, zzz=1)
    with pytest.raises(InputError, match=r"^policy 'every-n': takes no parameter\(s\) evry_n \(did you mean 'every_n'"):
        make_policy("every-n", evry_n=3)
    with pytest.raises(InputError, match=r"^policy 'gaus-slam': takes no parameter\(s\) tau \(did you mean 'tau_k'"):
        make_policy("gaus-slam", tau=0.1)
