"""The learned baselines (baselines/learned): fit and predict through the benchmark protocol,
learning beats skinning where the answer is learnable, causal streaming, a held-out groom,
checkpoints and resumption, clear errors, the training script (also under DDP)."""
import json
import os
from pathlib import Path

import pytest
import torch
import torch.multiprocessing as mp
from helpers import load_script
from learned_data import DenseGuides, toy_dataset

import ams_torch as at
from baselines.learned import TRAIN_DEFAULTS, Agnostic, Temporal, Upsampler
from baselines.learned.data import batch_windows, holdout, strand_subset, window_view
from baselines.learned.features import penetration_mm2, sdf_inputs, to_head, to_world
from baselines.protocol import MethodError, check_prediction, resolve_method, stream
from baselines.scene import make_sample
from baselines.skinning import LinearHairSkinning

G = 8
METHODS = ("upsampler", "agnostic", "collision", "temporal")
# tiny models that learn the toy case in 60 steps (seconds)
TINY = {"batch": 4, "strands": 48, "hidden": 64, "valid_every": 20, "valid_windows": 8, "lr": 5e-3, "steps": 60,
        "progress": False}
TINY_TEMPORAL = {"state": 32, "window": 8, "burn_in": 2}


def _opts(name, **kw):
    return {**TINY, **(TINY_TEMPORAL if name == "temporal" else {}), **kw}


@pytest.fixture(scope="module")
def toy(tmp_path_factory):
    """48 strands × 8 particles on a sphere head, a sphere swept through the hair, 8 sequences of 16 frames."""
    return toy_dataset(tmp_path_factory.mktemp("learned") / "a", sequences=8, frames=16, strands=48, particles=8,
                       guides=12, collider=True)


@pytest.fixture(scope="module")
def groom_b(tmp_path_factory):
    """Another groom (other roots, 80 strands), same particles per strand, its own motions."""
    return toy_dataset(tmp_path_factory.mktemp("learned") / "b", sequences=2, frames=16, strands=80, particles=8,
                       guides=12, seed=5, groom_seed=9, collider=True, split=(0.5, 0.0, 0.5))


def _splits(path, window=1):
    return (DenseGuides(path, G, split="train", window=window), DenseGuides(path, G, split="valid", window=window),
            DenseGuides(path, G, split="test", window=16))


def _samples(ds):
    out = []
    for i in range(len(ds)):
        s = make_sample(ds[i], ds)
        out.append((s, s.pop("positions")))
    return out


def _mean_mm(pred, ref):
    return float((pred - ref).norm(dim=-1).mean() * 1000)


def _skinning(sample):
    rest = sample["rest_positions"]
    return LinearHairSkinning(rest, rest[sample["guide_index"]], k=4)(sample["guide_positions"], sample["rotations"])


@pytest.fixture(scope="module")
def trained(toy):
    """Each method trained on the toy train split (validated on its valid split), with its test
    error and the skinning's."""
    train, valid, test = _splits(toy)
    samples = _samples(test)
    out = {}
    for name in METHODS:
        m = resolve_method(name, **_opts(name))
        m.fit(train, train[0]["guide_index"], valid=valid)
        preds = [check_prediction(name, m.predict(s), s) for s, _ in samples]
        err = sum(_mean_mm(p, r) for p, (_, r) in zip(preds, samples)) / len(samples)
        skin = sum(_mean_mm(_skinning(s), r) for s, r in samples) / len(samples)
        out[name] = {"method": m, "test_mm": err, "skinning_mm": skin, "preds": preds}
    return out, samples


@pytest.mark.parametrize("name", METHODS)
def test_method_fits_predicts_and_beats_skinning(trained, name):
    res, samples = trained
    r = res[name]
    m = r["method"]
    assert m.learned and m.name == name and m.result["steps"] <= TINY["steps"]
    s, ref = samples[0]
    assert r["preds"][0].shape == ref.shape == (16, 48, 8, 3)
    # the validation loss fell from the skinning's (step 0: the zero last layer) and the test error too
    valid = m.history["valid"]
    assert valid[0]["step"] == 0 and m.result["best_valid"] < 0.6 * valid[0]["loss"]
    assert r["test_mm"] < 0.8 * r["skinning_mm"], (r["test_mm"], r["skinning_mm"])
    # pinned particles follow the head: the residual is zero there
    pinned = int(s["num_pinned"][0])
    assert torch.allclose(r["preds"][0][:, :, :pinned], _skinning(s)[:, :, :pinned], atol=1e-5)


def test_untrained_models_are_the_skinning(toy):
    train, _, test = _splits(toy)
    s, _ = _samples(test)[0]
    item = train[0]
    for name in ("agnostic", "temporal", "upsampler"):
        m = resolve_method(name, **_opts(name))
        meta = m.data_meta(item)
        m.model = m.make_model(meta).eval()
        assert torch.allclose(m.predict(s), _skinning(s), atol=2e-6)


def test_temporal_stream_equals_predict(trained):
    res, samples = trained
    m = res["temporal"]["method"]
    assert m.causal
    s, _ = samples[0]
    pred = m.predict(s)
    assert torch.equal(stream(m, s), pred)
    # causal: the first frames do not depend on later frames
    cut = {k: (v[:5] if k in ("guide_positions", "rotations", "translations") else v) for k, v in s.items()}
    cut["collider_poses"] = [at.Pose(p.rotation[:5], p.translation[:5], check=False) for p in s["collider_poses"]]
    assert torch.equal(m.predict(cut), pred[:5])
    with pytest.raises(MethodError, match="not causal"):
        res["agnostic"]["method"].reset(s)


def test_agnostic_applies_to_another_groom(trained, groom_b):
    res, _ = trained
    ds = DenseGuides(groom_b, G, window=16)
    samples = _samples(ds)
    assert samples[0][0]["rest_positions"].shape == (80, 8, 3)
    skin = sum(_mean_mm(_skinning(s), r) for s, r in samples) / len(samples)
    for name in ("agnostic", "collision", "temporal"):
        m = res[name]["method"]
        err = sum(_mean_mm(check_prediction(name, m.predict(s), s), r) for s, r in samples) / len(samples)
        # (60 steps of the collision model mostly learn its penetration term: shape only)
        assert name == "collision" or err < 1.02 * skin, (name, err, skin)
    # the upsampler is bound to its groom and says so
    with pytest.raises(MethodError, match="use 'agnostic'"):
        res["upsampler"]["method"].predict(samples[0][0])


def test_collision_inputs_and_penetration_known_values():
    sphere = at.stages.SphereCollider(center=(0.0, 0.0, 0.0), radius=0.1)
    rot = torch.eye(3)[None]
    pose = [(rot, torch.zeros(1, 3))]
    # one strand of 2 vertices: 2 mm inside on +x, 30 mm outside on +y
    x = torch.tensor([[[[0.098, 0.0, 0.0], [0.0, 0.13, 0.0]]]])
    f = sdf_inputs(x, rot, [sphere], pose, reach=0.02).view(2, 4)
    assert torch.allclose(f[0], torch.tensor([-0.1, 1.0, 0.0, 0.0]), atol=1e-5)
    assert torch.allclose(f[1], torch.tensor([1.0, 0.0, 0.0, 0.0]), atol=1e-6)  # beyond reach: no normal
    mask = torch.ones(1, 2, 1)
    assert float(penetration_mm2(x, [sphere], pose, mask)) == pytest.approx(2.0, rel=1e-4)  # (4 + 0) / 2 mm²
    mask[0, 0] = 0
    assert float(penetration_mm2(x, [sphere], pose, mask)) == 0.0
    # the normal is given in the head frame: a head turned 90° about z sees +x as −y
    rz = torch.tensor([[[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]])
    f = sdf_inputs(x, rz, [sphere], pose, reach=0.02).view(2, 4)
    assert torch.allclose(f[0, 1:], torch.tensor([0.0, -1.0, 0.0]), atol=1e-6)
    # head frame round trip
    p = torch.randn(3, 5, 2, 3)
    r = at.geometry.pose.axis_angle_to_matrix(torch.randn(3, 3))
    t = torch.randn(3, 3)
    assert torch.allclose(to_world(to_head(p, r, t), r, t), p, atol=1e-5)


def test_collision_penetration_loss_reduces_penetration(trained):
    res, samples = trained
    from baselines.learned.features import collider_sdf, pose_tensors

    def inside(pred, s):
        d, _ = collider_sdf(pred.reshape(pred.shape[0], -1, 3), s["colliders"], pose_tensors(s["collider_poses"],
                                                                                             pred.shape[0]))
        pinned = torch.arange(pred.shape[2])[None, :] < s["num_pinned"][:, None]
        return float(((d.min(0).values < 0).view(pred.shape[:3]) & ~pinned).float().mean())

    skin = sum(inside(_skinning(s), s) for s, _ in samples)
    col = sum(inside(p, s) for p, (s, _) in zip(res["collision"]["preds"], samples))
    assert col <= skin


def test_data_helpers(toy):
    train, valid, _ = _splits(toy)
    assert torch.equal(batch_windows(3, 5, 17, 2), batch_windows(3, 5, 17, 2))
    seen = torch.cat([batch_windows(k, 5, 17, 2) for k in range(17)])[:17 * 5]
    assert torch.equal(torch.bincount(seen, minlength=17), torch.full((17,), 5))  # each epoch a permutation
    assert torch.equal(strand_subset(10, 20, 1), torch.arange(10))
    sub = strand_subset(100, 7, 1)
    assert sub.numel() == 7 and sub.unique().numel() == 7 and torch.equal(sub, strand_subset(100, 7, 1))
    w = window_view(train, 5, 2)
    assert w[0]["positions"].shape[0] == 5 and w[1]["start"] == 2 and len(train[0]["positions"]) == 1
    keep, held = holdout(train, 0.5)
    ks = {keep[i]["sequence"] for i in range(len(keep))}
    hs = {held[i]["sequence"] for i in range(len(held))}
    assert ks and hs and not ks & hs and len(keep) + len(held) == len(train)


def test_checkpoint_round_trip_and_resume(toy, tmp_path):
    train, valid, test = _splits(toy)
    s, _ = _samples(test)[0]
    gi = train[0]["guide_index"]
    kw = _opts("temporal", steps=8, valid_every=4, patience=100)
    path = tmp_path / "sub" / "t.pt"  # a missing folder
    a = Temporal(checkpoint=path, **kw).fit(train, gi, valid=valid)
    assert path.exists()
    pred = a.predict(s)
    # the same training finds the finished checkpoint and loads it (no step taken)
    b = Temporal(checkpoint=path, **kw).fit(train, gi, valid=valid)
    assert torch.equal(b.predict(s), pred) and b.history == a.history
    assert torch.equal(Temporal().load(str(path)).predict(s), pred)
    # resumption: 4 steps, then on to 8, equals 8 straight
    part = tmp_path / "r.pt"
    Temporal(checkpoint=part, **{**kw, "steps": 4}).fit(train, gi, valid=valid)
    c = Temporal(checkpoint=part, **kw).fit(train, gi, valid=valid)
    assert c.history["train"] == pytest.approx(a.history["train"], rel=1e-6)
    assert torch.allclose(c.predict(s), pred, atol=1e-6)
    # another model configuration does not match: trained anew, with a warning
    with pytest.warns(UserWarning, match="training anew"):
        Temporal(checkpoint=path, **{**kw, "state": 16}).fit(train, gi, valid=valid)


def test_clear_errors(toy, groom_b, trained):
    train, valid, test = _splits(toy)
    s, _ = _samples(test)[0]
    with pytest.raises(MethodError, match="not trained"):
        Agnostic().predict(s)
    with pytest.raises(TypeError, match="unknown option"):
        Agnostic(hiden=3)
    with pytest.raises(ValueError, match="steps must be an integer"):
        Upsampler(steps=0)
    with pytest.raises(ValueError, match="burn_in < window"):
        Temporal(window=4, burn_in=4)
    m = trained[0]["agnostic"]["method"]
    bad = dict(s)
    del bad["rest_positions"]
    with pytest.raises(ValueError, match=r"lacks \['rest_positions'\]"):
        m.predict(bad)
    bad = dict(s, rotations=s["rotations"][:3])
    with pytest.raises(ValueError, match=r"rotations must have shape \(16, 3, 3\)"):
        m.predict(bad)
    short = dict(s, guide_positions=s["guide_positions"][:, :, :6], rest_positions=s["rest_positions"][:, :6])
    with pytest.raises(MethodError, match="N = 6 particles per strand; the model was trained with N = 8"):
        m.predict(short)
    with pytest.raises(ValueError, match="guide_index"):
        Agnostic(**_opts("agnostic", steps=1)).fit(train, torch.arange(G), valid=valid)
    # the upsampler validates on its own groom: another groom's valid split is replaced by held-out train sequences
    with pytest.warns(UserWarning, match="no window of the valid split suits"):
        up = Upsampler(**_opts("upsampler", steps=2)).fit(train, train[0]["guide_index"],
                                                          valid=DenseGuides(groom_b, G, split="train"))
    assert up.result["steps"] == 2
    # a train split of two grooms and a valid split of a third: the upsampler trains on one groom and
    # validates on held-out sequences of that groom (not of the other)
    mixed = DenseGuides(toy_dataset(Path(groom_b).parent / "mixed", strands="{ cycle = [48, 56] }", sequences=8,
                                    split=(0.75, 0.25, 0.0)), G, split="train")
    assert {mixed[i]["rest_positions"].shape[0] for i in range(len(mixed))} == {48, 56}
    with pytest.warns(UserWarning, match="no window of the valid split suits"):
        up = Upsampler(**_opts("upsampler", steps=2)).fit(mixed, mixed[0]["guide_index"],
                                                          valid=DenseGuides(groom_b, G, split="train"))
    assert up.result["steps"] == 2
    # the upsampler trains on one groom only
    both = torch.utils.data.ConcatDataset([train, DenseGuides(groom_b, G, split="train")])
    with pytest.raises(ValueError, match="bound to one groom"):
        Upsampler(**_opts("upsampler", steps=40)).fit(both, train[0]["guide_index"], valid=valid)


def test_held_out_sequences_stay_out_of_a_new_view(toy):
    from baselines.learned.data import holdout, item_sequences, window_view

    train = DenseGuides(toy, G, split="train")
    part, held = holdout(train, 0.5)
    seqs, out = set(item_sequences(part)), set(item_sequences(held))
    assert seqs and out and not seqs & out
    for window in (None, 4):  # re-windowing the train part (what training does) keeps the held-out part out
        assert set(item_sequences(window_view(part, window))) == seqs
    assert set(item_sequences(window_view(part, None, keep=sorted(out)))) == set()


def test_learned_methods_are_builtins():
    for name in METHODS:
        # the benchmark's context is given where the factory takes it; the user's options must all be taken
        m = resolve_method(name, {"device": "cpu", "not_in_the_context": 1}, steps=3)
        assert m.learned and m.options["steps"] == 3 and str(m.device) == "cpu"
        with pytest.raises(MethodError, match="takes no option"):
            resolve_method(name, {"device": "cpu"}, not_an_option=1)
    assert set(TRAIN_DEFAULTS) <= set(Agnostic.defaults())


# -- the training script ------------------------------------------------------------------------
def _script(toy):
    mod = load_script("train_interp")
    mod.open_split = lambda data, split, guides: (None if split == "valid" else DenseGuides(data, guides, split=split))
    return mod


def _argv(toy, out, method="agnostic", steps=6, extra=()):
    return ["--method", method, "--data", toy, "--guides", str(G), "--out", str(out), "--steps", str(steps),
            "--batch", "4", "--strands", "16", "--valid-every", "3", "--patience", "100", "--option", "hidden=16",
            "--option", "valid_windows=4", "--no-progress", "--threads", "1", *extra]


def test_train_interp_end_to_end(toy, tmp_path):
    mod = _script(toy)
    out = tmp_path / "missing" / "run"
    res = mod.main(_argv(toy, out))
    assert (out / "model.pt").exists()
    hist = json.loads((out / "history.json").read_text())
    summary = json.loads((out / "summary.json").read_text())
    assert len(hist["train"]) == 6 and [v["step"] for v in hist["valid"]] == [0, 3, 6]
    assert summary["steps"] == 6 and summary["method"] == "agnostic" and summary["options"]["hidden"] == 16
    # the model is the method the benchmark loads
    m = Agnostic().load(str(out / "model.pt"))
    test = DenseGuides(toy, G, split="test", window=4)
    s = make_sample(test[0], test)
    s.pop("positions")
    assert torch.equal(m.predict(s), res["method"].predict(s))
    # on to 9 steps: resumes; --restart starts over
    again = mod.main(_argv(toy, out, steps=9))
    assert again["result"]["steps"] == 9 and again["result"]["history"]["train"][:6] == hist["train"]
    mod.main(_argv(toy, out, steps=2, extra=["--restart"]))
    assert len(json.loads((out / "history.json").read_text())["train"]) == 2
    with pytest.raises(ValueError, match=r"takes no option\(s\) \['hiden'\]"):
        mod.main(_argv(toy, tmp_path / "x", extra=["--option", "hiden=3"]))


def _ddp_worker(rank, world, toy, argv, store):
    os.environ.update(RANK=str(rank), WORLD_SIZE=str(world), LOCAL_RANK=str(rank), MASTER_ADDR="127.0.0.1",
                      GLOO_SOCKET_IFNAME="lo")
    torch.set_num_threads(1)
    _script(toy).main(argv + ["--init-method", f"file://{store}"])


def test_train_interp_ddp_two_processes_match_one(toy, tmp_path):
    one = _script(toy).main(_argv(toy, tmp_path / "one", method="upsampler"))["result"]["history"]
    argv = _argv(toy, tmp_path / "two", method="upsampler")
    # file:// rendezvous (no TCP store); gloo on the loopback interface only
    mp.start_processes(_ddp_worker, args=(2, toy, argv, str(tmp_path / "store")), nprocs=2, join=True,
                       start_method="spawn")
    two = json.loads((tmp_path / "two" / "history.json").read_text())
    assert len(two["train"]) == 6
    assert two["train"] == pytest.approx(one["train"], rel=1e-5)
    assert [v["loss"] for v in two["valid"]] == pytest.approx([v["loss"] for v in one["valid"]], rel=1e-5)
    a = torch.load(tmp_path / "one" / "model.pt", weights_only=False)["model"]
    b = torch.load(tmp_path / "two" / "model.pt", weights_only=False)["model"]
    for k in a:
        assert torch.allclose(a[k], b[k], rtol=1e-4, atol=1e-6), k
