"""Denoiser designs side by side: which one learns to *compare* render and crop?

Every candidate (``NetworkConfig.design``, see ``monose3.method.config.DESIGNS``) trains on the
same fixed pool of training samples, in the same order, for the same number of samples, on
one CPU thread, and is judged on a held-out pool made from other frames:

* the three parts of Eq. 10 (xy, rot, z; metres) by t bucket (1-10, 11-20, 21-50, 51-100)
  at a few points along training, against the identity update (zero network output);
* the render ablation at the end: the render replaced by zeros, or by another held-out
  sample's render, as the % change of the xy and rot parts (a network that compares render
  and crop gets much worse; one that reads the crop alone does not).

The pools are built once with the training pipeline itself (``monose3.training.loop.BatchMaker``:
forward process, crop geometry, image crop or synthetic scene, render at H_t) from a DREAM
folder, or from scenes synthesised on the fly (``--train-data synthetic``), and cached as
``.npz``, so each candidate runs network-bound. Candidates can run in separate processes (``--designs`` one each) and be
put together afterwards with ``--report``::

    python -m monose3.apps.cli generate --out train --num 600 --seed 1 --size 320x240
    python -m monose3.apps.cli generate --out held --num 200 --seed 2 --size 320x240
    python benchmarks/denoiser_designs.py --train-data train --held-data held \\
        --pool-dir pool --out results --designs concat flow-solve --samples 8000
    python benchmarks/denoiser_designs.py --out results --report

Recipes: ``--rotation-output`` (``NetworkConfig.rotation_output``), ``--rot-weight``,
``--backbone efficientnet-lite0`` (the ImageNet-pretrained trunk), ``--train-t-max`` (train on small t only),
``--lr``, ``--flow-weight`` (the ``cost-volume`` design's auxiliary displacement-field loss;
its held-out error, with the render as is, zeroed and swapped, is then reported too), named
with ``--tag``. ``--sanity clean`` / ``--sanity rotation`` build pools of
clean synthetic scenes, the second with H_0 given H_t's translation, so render and crop
differ by a rotation alone: the sanity task of whether rotation is learnable at all
(docs/DESIGNS.md).

Models trained elsewhere (e.g. ``monose3 train --synthetic --design D`` on a GPU) are
judged the same way with ``--weights RUN...`` (run folders or checkpoints), on a held-out
pool of the same preset (``--preset``; ``--held-data synthetic`` draws it on the fly).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

from monose3.errors import Monose3Error, run_reporting_errors
from monose3.method.config import (
    BACKBONES,
    DESIGNS,
    PRETRAINED_TRUNK_DESIGNS,
    ROTATION_OUTPUTS,
    Config,
    get_preset,
    with_section,
)
from monose3.method.denoiser import Denoiser, DenoiserOutput
from monose3.method.designs import FIELD_DESIGNS, build_denoiser
from monose3.method.flow_pose import field_targets
from monose3.method.loss import disentangled_parts, flow_errors
from monose3.training.loop import learning_rate
from monose3.training.objective import batch_surface, train_step

BUCKETS = ((1, 10), (11, 20), (21, 50), (51, 100))
PARTS = ("xy", "rot", "z")
NUM_POINTS = 512  # model points kept per sample for Eq. 10 (of 2000)
Pool = dict[str, torch.Tensor]


# ---- sample pools ---------------------------------------------------------------------------


SANITY = ("none", "clean", "rotation")


def _rotation_only_batch(maker, config: Config, seed: int, step: int) -> dict[str, torch.Tensor]:
    """A clean synthetic batch whose H_0 has H_t's translation: render and crop differ by the
    rotation about the centroid alone (the sanity task: is rotation learnable at all?)."""
    from monose3.method.pose_space import base_frame
    from monose3.training.samples import denoising_batch, noisy_views, step_generator
    from monose3.training.synthetic import synthesize_crops

    net = config.network
    scenes = dict(maker.next_scenes())
    joints = scenes["joints"].numpy()
    views = noisy_views(
        maker.robot, maker.noiser, config, scenes["pose"], joints, scenes["K"], step_generator(seed, step)
    )
    views.pose_ref_0 = views.pose_ref_0.clone()
    views.pose_ref_0[:, :3, 3] = views.pose_ref_t[:, :3, 3]
    scenes["pose"] = base_frame(views.pose_ref_0, views.centroid).to(scenes["pose"].dtype)
    crops = synthesize_crops(
        maker.renderer, scenes, views, net.render_size, net.input_size, maker.profile, maker.photos,
        step_generator(seed, step), torch.device("cpu"),
    )  # fmt: skip
    return denoising_batch(views, crops, joints, maker.renderer)


def build_pool(data_dir: str, config: Config, num: int, seed: int, sanity: str = "none") -> dict[str, np.ndarray]:
    """``num`` training samples (steps 0.. of a run with this seed), images as uint8; ``data_dir``
    is a DREAM folder or ``"synthetic"``. ``sanity``: ``clean`` synthetic scenes
    (the ``clean`` scene profile), or ``rotation``: clean scenes with H_0's translation set to H_t's."""
    from monose3.data.datasets import load_datasets
    from monose3.training.loop import BatchMaker, Sources

    config = with_section(config, "train", seed=seed, num_workers=0)
    if sanity != "none":
        sources = Sources(synthetic=True, profile="clean")
    elif data_dir == "synthetic":
        sources = Sources(synthetic=True)
    else:
        sources = Sources(load_datasets([data_dir], config.robot))
    maker = BatchMaker(config, sources, torch.device("cpu"), 0, 0, 1)
    keep = np.random.default_rng(0).choice(2000, NUM_POINTS, replace=False)
    steps = range(-(-num // config.train.batch_size))
    if sanity == "rotation":
        batches = [_rotation_only_batch(maker, config, seed, step) for step in steps]
    else:
        batches = [maker.batch(step)[1] for step in steps]
    pool = {k: torch.cat([b[k] for b in batches])[:num].numpy() for k in batches[0]}
    for key in ("render", "crop"):
        pool[key] = np.round(pool[key] * 255).astype(np.uint8)
    pool["points_ref"] = pool["points_ref"][:, keep]
    return pool


def load_pool(path: Path, data_dir: str | None, config: Config, num: int, seed: int, sanity: str = "none") -> Pool:
    """The cached pool at ``path``, built from ``data_dir`` first when missing or too small."""
    if path.is_file():
        cached = dict(np.load(path))
        if "depth" not in cached:
            raise Monose3Error(f"the pool {path} holds no render depth (built before flow-solve); delete it to rebuild")
        if len(cached["t"]) >= num:
            return {k: torch.from_numpy(v[:num]) for k, v in cached.items()}
    if data_dir is None:
        raise Monose3Error(f"no sample pool at {path}; pass --train-data/--held-data to build it")
    tick = time.perf_counter()
    pool = build_pool(data_dir, config, num, seed, sanity)
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez(path, **pool)
    print(f"built {num} samples from {data_dir} in {time.perf_counter() - tick:.0f} s -> {path}", flush=True)
    return {k: torch.from_numpy(v) for k, v in pool.items()}


def batch_of(pool: Pool, idx: torch.Tensor, config: Config, with_surface: bool = True) -> dict[str, torch.Tensor]:
    """Float batch of pool rows ``idx``, with the render's visible surface (flow_pose.render_surface)
    unless ``with_surface`` is off (a training step finds it itself)."""
    batch = {k: v[idx] for k, v in pool.items()}
    for key in ("render", "crop"):
        batch[key] = batch[key].float() / 255.0
    batch["depth"] = batch["depth"].float()
    if with_surface:
        batch["surface"] = batch_surface(batch)
    return batch


# ---- training and evaluation ----------------------------------------------------------------


def model_out(model: Denoiser, batch: dict, render: torch.Tensor | None = None) -> DenoiserOutput:
    """The network's output on ``batch``, optionally with another ``render`` (ablation: the
    image only; the geometry of H_t stays this sample's)."""
    render = batch["render"] if render is None else render
    return model(render, batch["crop"], batch["t"], batch["surface"])


def parts_of(raw: torch.Tensor, batch: dict[str, torch.Tensor], config: Config) -> dict[str, torch.Tensor]:
    """Per-sample parts of Eq. 10 for ``raw``."""
    args = (batch["pose_ref_t"], batch["pose_ref_0"], batch["K_crop"], batch["points_ref"])
    return disentangled_parts(raw, *args, config.network.render_size[0])


def flow_targets_of(batch: dict, config: Config, flow: torch.Tensor):
    """The displacement-field target and mask of ``batch`` on ``flow``'s grid (flow_pose.field_targets)."""
    return field_targets(batch["surface"], batch["pose_ref_0"], config.network.render_size, tuple(flow.shape[-2:]))


@torch.no_grad()
def evaluate(model: Denoiser | None, held: Pool, config: Config, ablation: str = "none") -> dict[str, np.ndarray]:
    """Per-sample Eq. 10 parts on the held-out pool; ``model=None`` is the identity update.

    ``ablation``: ``none``, ``zero`` (render replaced by zeros) or ``swap`` (by the next
    sample's render).
    """
    out: dict[str, list] = {k: [] for k in PARTS}
    if model is not None:
        model.eval()
    n = len(held["t"])
    for start in range(0, n, 32):
        idx = torch.arange(start, min(n, start + 32))
        batch = batch_of(held, idx, config)
        if model is None:
            raw = torch.zeros(len(idx), 9)
        else:
            render = {"none": None, "zero": torch.zeros_like(batch["render"])}.get(ablation)
            if ablation == "swap":
                render = batch_of(held, (idx + 1) % n, config)["render"]
            raw = model_out(model, batch, render).raw
        for k, v in parts_of(raw.float(), batch, config).items():
            out[k].append(v.numpy())
    return {k: np.concatenate(v) for k, v in out.items()}


@torch.no_grad()
def field_ceiling(held: Pool, config: Config, strides: tuple[int, ...] = (16, 8, 4)) -> dict[int, dict]:
    """What the flow-solve design reaches when its field is the true one: Eq. 10 parts by t
    bucket of the pose :func:`~monose3.method.flow_pose.pose_from_field` solves from the target
    field (cell means of the visible surface's moves) at each stride, all cells trusted alike."""
    from monose3.method.flow_pose import pose_from_field
    from monose3.method.update import true_update, update_to_raw

    batch = batch_of(held, torch.arange(len(held["t"])), config)
    width, height = config.network.render_size
    out = {}
    for stride in strides:
        field, mask = field_targets(
            batch["surface"], batch["pose_ref_0"], (width, height), (height // stride, width // stride)
        )
        pose_0 = pose_from_field(field, mask.float(), batch["surface"], (width, height))
        raw = update_to_raw(*true_update(batch["pose_ref_t"], pose_0, batch["K_crop"]), width)
        out[stride] = bucket_means({k: v.numpy() for k, v in parts_of(raw, batch, config).items()}, held["t"].numpy())
    return out


def identity_gradients(held: Pool, config: Config) -> dict[str, float]:
    """Median over held-out samples of |d part / d its own raw outputs| at the identity update
    (raw = 0): how hard each part of Eq. 10 pulls on the network's output at init."""
    n = len(held["t"])
    batch = batch_of(held, torch.arange(n), config)
    raw = torch.zeros(n, 9, requires_grad=True)
    parts = parts_of(raw, batch, config)
    own = {"xy": slice(0, 2), "rot": slice(2, 8), "z": slice(8, 9)}
    out = {}
    for key in PARTS:
        (grad,) = torch.autograd.grad(parts[key].sum(), raw, retain_graph=True)
        out[key] = float(grad[:, own[key]].norm(dim=1).median())
    return out


def bucket_means(parts: dict[str, np.ndarray], t: np.ndarray) -> dict[str, dict[str, float]]:
    """Mean of each part by t bucket (and over all t as ``all``)."""
    out = {}
    for lo, hi in BUCKETS:
        sel = (t >= lo) & (t <= hi)
        # An empty bucket (a small held-out pool) is NaN, printed as such, without numpy's warning.
        out[f"{lo}-{hi}"] = {k: float(v[sel].mean()) if sel.any() else float("nan") for k, v in parts.items()}
    out["all"] = {k: float(v.mean()) for k, v in parts.items()}
    return out


def train_design(design: str, config: Config, train: Pool, held: Pool, args: argparse.Namespace) -> dict:
    """Train one design for ``args.samples`` samples, evaluating ``args.evals`` times; ablate at the end."""
    config = with_section(
        config,
        "network",
        design=design,
        backbone=args.backbone or config.network.backbone,
        rotation_output=args.rotation_output,
        field_stride=args.field_stride,
    )
    config = with_section(config, "train", rot_weight=args.rot_weight, flow_weight=args.flow_weight)
    if args.lr is not None:
        config = with_section(config, "train", lr=args.lr)
    torch.manual_seed(args.seed)
    model = build_denoiser(config.network)
    optimizer = torch.optim.Adam(model.parameters(), lr=config.train.lr)
    gen = torch.Generator().manual_seed(args.seed)  # the same batch order for every design
    rows = torch.arange(len(train["t"]))
    if args.train_t_max is not None:  # a recipe: train on small t only (visible rotation differences)
        rows = rows[train["t"] <= args.train_t_max]
    order = torch.cat([rows[torch.randperm(len(rows), generator=gen)] for _ in range(args.samples // len(rows) + 1)])
    steps, bs = args.samples // args.batch_size, args.batch_size
    eval_at = {round(steps * (i + 1) / args.evals) for i in range(args.evals)}
    t_held = held["t"].numpy()
    curve, tick, train_s, window = [], time.perf_counter(), 0.0, []
    for step in range(steps):
        model.train()
        batch = batch_of(train, order[step * bs : (step + 1) * bs], config, with_surface=False)
        _, parts = train_step(model, optimizer, batch, config, learning_rate(step, config))
        window.append([parts[k] for k in PARTS])
        if step + 1 in eval_at:
            train_s += time.perf_counter() - tick
            row = {"samples": (step + 1) * bs, "train_s": train_s}
            row["train_parts"] = dict(zip(PARTS, np.mean(window, axis=0).tolist(), strict=True))
            window = []
            row["buckets"] = bucket_means(evaluate(model, held, config), t_held)
            curve.append(row)
            by_t = "  ".join(f"t {b}: {'/'.join(f'{v:.4f}' for v in p.values())}" for b, p in row["buckets"].items())
            print(f"{design}: {row['samples']} samples, {train_s:.0f} s, held-out xy/rot/z {by_t}", flush=True)
            tick = time.perf_counter()
    normal = evaluate(model, held, config)
    ablations, ablations_by_t = render_ablation(model, held, config, normal)
    if args.save_model:
        from monose3.training.checkpoints import save_checkpoint

        state = {"model": model.state_dict(), "config": config.to_dict(), "step": steps, "samples": steps * bs}
        save_checkpoint(Path(args.out) / f"{design}{'_' + args.tag if args.tag else ''}.pt", state)
    recipe = {
        "rotation_output": args.rotation_output,
        "lr": config.train.lr,
        "train_t_max": args.train_t_max,
        "backbone": config.network.backbone,
        "flow_weight": args.flow_weight,
        "crop_jitter": args.crop_jitter,
        "field_stride": args.field_stride,
    }
    recipe["pool"] = len(train["t"])
    name = design + (f" [{args.tag}]" if args.tag else "")
    result = {
        "design": name,
        "rot_weight": args.rot_weight,
        "recipe": recipe,
        "curve": curve,
        "ablation_pct": ablations,
        "ablation_pct_by_t": ablations_by_t,
    }
    return result | flow_check(model, held, config)


def render_ablation(model: Denoiser, held: Pool, config: Config, normal: dict[str, np.ndarray]) -> tuple[dict, dict]:
    """How much each held-out part grows (%) when the render is zeroed or swapped for another
    sample's: over all samples (the issue's measure) and by t bucket (the all-t mean is
    dominated by large t, where a model trained on small t barely moves)."""
    t = held["t"].numpy()
    overall, by_t = {}, {}
    for name in ("zero", "swap"):
        ablated = evaluate(model, held, config, name)
        overall[name] = _growth_pct(ablated, normal, np.ones(len(t), dtype=bool))
        rows = {f"{lo}-{hi}": (t >= lo) & (t <= hi) for lo, hi in BUCKETS}
        by_t[name] = {b: _growth_pct(ablated, normal, r) for b, r in rows.items() if r.any()}
    return overall, by_t


def _growth_pct(ablated: dict[str, np.ndarray], normal: dict[str, np.ndarray], rows: np.ndarray) -> dict:
    return {k: float(100.0 * (ablated[k][rows].mean() / normal[k][rows].mean() - 1.0)) for k in PARTS}


@torch.no_grad()
def flow_check(model: Denoiser, held: Pool, config: Config) -> dict:
    """For a design that predicts the displacement field (``cost-volume``): its held-out L1 error
    by t bucket (units of the render width), with the render as is, zeroed and swapped, and the
    error of a zero field; ``{}`` for the other designs."""
    if not model.predicts_field:
        return {}
    model.eval()
    n, errors = len(held["t"]), {k: [] for k in ("render", "zero", "swap", "zero field")}
    for start in range(0, n, 32):
        idx = torch.arange(start, min(n, start + 32))
        batch = batch_of(held, idx, config)
        renders = {"render": batch["render"], "zero": torch.zeros_like(batch["render"])}
        renders["swap"] = batch_of(held, (idx + 1) % n, config)["render"]
        for name, render in renders.items():
            flow = model_out(model, batch, render).field
            target, mask = flow_targets_of(batch, config, flow)
            errors[name].append(flow_errors(flow, target, mask).numpy())
            if name == "render":
                errors["zero field"].append(flow_errors(torch.zeros_like(flow), target, mask).numpy())
    return {"flow_l1": bucket_means({k: np.concatenate(v) for k, v in errors.items()}, held["t"].numpy())}


def judge_weights(path: str, config: Config, held: Pool) -> dict:
    """A trained run's held-out parts by t bucket and its render ablation, as a one-point curve."""
    from monose3.training.checkpoints import load_model

    model, saved = load_model(path)
    if saved.network.render_size != config.network.render_size:
        raise Monose3Error(f"{path} renders at {saved.network.render_size}; pass --preset {saved.preset}")
    config = with_section(config, "network", design=saved.network.design)
    state_samples = _samples_seen(path)
    normal = evaluate(model, held, config)
    ablations, ablations_by_t = render_ablation(model, held, config, normal)
    row = {"samples": state_samples, "train_s": 0.0, "buckets": bucket_means(normal, held["t"].numpy())}
    name = f"{saved.network.design} [{Path(path).name}]"
    result = {"design": name, "rot_weight": saved.train.rot_weight, "curve": [row], "ablation_pct": ablations}
    result["ablation_pct_by_t"] = ablations_by_t
    return result | flow_check(model, held, config)


def _samples_seen(path: str) -> int:
    from monose3.training.checkpoints import read_weights

    state = read_weights(path)
    return int(state.get("samples", 0))


# ---- report ---------------------------------------------------------------------------------


def verdict(result: dict, identity: dict) -> dict[str, bool]:
    """The design study's targets: render ablation raises xy and rot by >= 30 %; rot below identity in every bucket."""
    last = result["curve"][-1]["buckets"]
    abl = result["ablation_pct"]
    return {
        "ablation_ge_30pct": all(abl[a][k] >= 30.0 for a in ("zero", "swap") for k in ("xy", "rot")),
        "rot_below_identity": all(last[b]["rot"] < identity[b]["rot"] for b in identity if b != "all"),
    }


def print_table(results: list[dict], identity: dict) -> None:
    buckets = [f"{lo}-{hi}" for lo, hi in BUCKETS]
    head = f"{'design':<22}{'samples':>8}{'train s':>8}  " + "  ".join(f"{'t ' + b + ' xy/rot/z':>22}" for b in buckets)
    print(head + f"  {'zero xy/rot %':>14}  {'swap xy/rot %':>14}  targets")

    def cells(b: dict) -> str:
        return "  ".join(f"{b[k]['xy']:>6.3f} {b[k]['rot']:>6.3f} {b[k]['z']:>6.3f}     " for k in buckets)

    print(f"{'identity':<22}{'-':>8}{'-':>8}  " + cells(identity))
    for r in results:
        last, abl = r["curve"][-1], r["ablation_pct"]
        v = verdict(r, identity)
        name = r["design"] + (f" (rot x{r['rot_weight']:g})" if r["rot_weight"] != 1.0 else "")
        pct = "  ".join(f"{abl[a]['xy']:>+6.0f} {abl[a]['rot']:>+6.0f}" for a in ("zero", "swap"))
        yes = {True: "yes", False: "no"}
        print(
            f"{name:<22}{last['samples']:>8}{last['train_s']:>8.0f}  {cells(last['buckets'])}  {pct}"
            f"  abl>=30%:{yes[v['ablation_ge_30pct']]} rot<id:{yes[v['rot_below_identity']]}"
        )
    for r in results:  # the ablation by t bucket (results since it was recorded)
        by_t = r.get("ablation_pct_by_t")
        if by_t:
            cells = "  ".join(
                f"t {b} {by_t['zero'][b]['xy']:+.0f}/{by_t['zero'][b]['rot']:+.0f} "
                f"{by_t['swap'][b]['xy']:+.0f}/{by_t['swap'][b]['rot']:+.0f}"
                for b in by_t["zero"]
            )
            print(f"  {r['design']}: render zeroed / swapped, xy/rot % by t: {cells}")
    for r in results:  # the cost-volume design's displacement field (flow_check)
        flow = r.get("flow_l1", {})
        for kind in flow.get("all", {}):
            cells = "  ".join(f"t {b} {flow[b][kind]:.4f}" for b in [*buckets, "all"])
            print(f"  {r['design']}: flow L1 with {kind}: {cells}")


def plot(results: list[dict], identity: dict, path: Path) -> Path:
    """Held-out rot and xy parts against training samples, one panel per t bucket, identity dashed."""
    from monose3.report.plots import new_figure, save_figure

    fig = new_figure((14.0, 7.0))
    for row, part in enumerate(("rot", "xy")):
        for col, (lo, hi) in enumerate(BUCKETS):
            key = f"{lo}-{hi}"
            ax = fig.add_subplot(2, len(BUCKETS), row * len(BUCKETS) + col + 1)
            for r in results:
                xs = [c["samples"] for c in r["curve"]]
                ax.plot(xs, [c["buckets"][key][part] for c in r["curve"]], marker="o", label=_label(r))
            ax.axhline(identity[key][part], color="k", linestyle="--", label="identity update")
            ax.set_title(f"{part} part, t {key}")
            ax.set_xlabel("training samples")
            ax.set_ylabel("Eq. 10 part (m)")
            ax.grid(True, alpha=0.4)
    fig.axes[0].legend(loc="best", fontsize=7)
    fig.tight_layout()
    return save_figure(fig, path)


def _label(result: dict) -> str:
    return result["design"] + (f" rot x{result['rot_weight']:g}" if result["rot_weight"] != 1.0 else "")


def report(out: Path) -> None:
    results = [json.loads(p.read_text()) for p in sorted(out.glob("result_*.json"))]
    if not results:
        raise Monose3Error(f"no result_*.json in {out}; run some designs first")
    identity = json.loads((out / "identity.json").read_text())
    print_table(results, identity)
    summary = {"identity": identity, "results": results, "verdict": {_label(r): verdict(r, identity) for r in results}}
    (out / "summary.json").write_text(json.dumps(summary, indent=1))
    print(f"wrote {out / 'summary.json'} and {plot(results, identity, out / 'designs.png')}")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--train-data", help="DREAM folder the training pool is built from (first run)")
    p.add_argument("--held-data", help="DREAM folder (other frames) the held-out pool is built from")
    p.add_argument("--pool-dir", default="/tmp/monose3_design_pools", help="where the pools are cached")
    p.add_argument("--pool-size", type=int, default=4000, help="training samples in the pool")
    p.add_argument("--held-size", type=int, default=480, help="held-out samples")
    p.add_argument(
        "--sanity",
        default="none",
        choices=SANITY,
        help="pools of clean synthetic scenes (clean), also with H_0's translation = H_t's (rotation) [none]",
    )
    p.add_argument("--designs", nargs="*", default=[], choices=DESIGNS)
    p.add_argument("--weights", nargs="*", default=[], help="trained run folders / checkpoints to judge instead")
    p.add_argument("--preset", default="cpu", help="preset of the pools and the models (render size) [cpu]")
    p.add_argument("--samples", type=int, default=8000, help="training samples per design")
    p.add_argument("--evals", type=int, default=4, help="held-out evaluations along training")
    p.add_argument("--batch-size", type=int, default=16)
    p.add_argument("--rot-weight", type=float, default=1.0, help="weight of Eq. 10's rotation part in training")
    p.add_argument(
        "--rotation-output", default="6d", choices=list(ROTATION_OUTPUTS), help="NetworkConfig.rotation_output"
    )
    p.add_argument(
        "--backbone",
        choices=BACKBONES,
        help="NetworkConfig.backbone: resnet18/34 from scratch or efficientnet-lite0 "
        "(ImageNet-pretrained; cost-volume, flow-solve) [the preset's]",
    )
    p.add_argument(
        "--flow-weight", type=float, default=0.0, help="weight of the cost-volume design's auxiliary flow loss"
    )
    p.add_argument("--field-stride", type=int, default=8, help="NetworkConfig.field_stride (flow-solve) [8]")
    p.add_argument("--lr", type=float, help="Adam learning rate after warm-up [the preset's, 3e-4]")
    p.add_argument("--train-t-max", type=int, help="train on samples with t <= this only")
    p.add_argument(
        "--crop-jitter", type=float, default=0.0, help="TrainConfig.crop_jitter of the training pool (held-out: 0)"
    )
    p.add_argument("--tag", default="", help="recipe name, added to the design's name and its result file")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--save-model", action="store_true", help="also save OUT/<design>.pt")
    p.add_argument("--out", default="/tmp/monose3_designs", help="folder for result_*.json, summary.json, PNG")
    p.add_argument(
        "--field-ceiling", action="store_true", help="also print what flow-solve reaches with the true field"
    )
    p.add_argument("--report", action="store_true", help="only print the table and plot of the results in --out")
    args = p.parse_args(argv)
    torch.set_num_threads(args.threads)
    out = Path(args.out)
    if args.report:
        report(out)
        return 0
    if args.flow_weight and set(args.designs) - set(FIELD_DESIGNS):
        raise Monose3Error(f"--flow-weight needs --designs among {FIELD_DESIGNS}, the designs that predict a field")
    if args.backbone == BACKBONES[2] and set(args.designs) - set(PRETRAINED_TRUNK_DESIGNS):
        raise Monose3Error(f"--backbone {args.backbone} needs --designs among {PRETRAINED_TRUNK_DESIGNS}")
    config = get_preset(args.preset)
    pools = Path(args.pool_dir) / args.preset
    if args.sanity != "none":
        pools = pools / args.sanity
        args.train_data = args.held_data = "synthetic"
    held = load_pool(pools / "held.npz", args.held_data, config, args.held_size, 1, args.sanity)
    jittered = with_section(config, "train", crop_jitter=args.crop_jitter)
    name = f"train_jitter{args.crop_jitter:g}.npz" if args.crop_jitter else "train.npz"
    train = load_pool(pools / name, args.train_data, jittered, args.pool_size, 0, args.sanity) if args.designs else None
    out.mkdir(parents=True, exist_ok=True)
    identity = bucket_means(evaluate(None, held, config), held["t"].numpy())
    (out / "identity.json").write_text(json.dumps(identity, indent=1))
    if args.field_ceiling:
        ceiling = field_ceiling(held, config)
        (out / "field_ceiling.json").write_text(json.dumps(ceiling, indent=1))
        for stride, buckets in ceiling.items():
            cells = "  ".join(f"t {b} {'/'.join(f'{v:.4f}' for v in p.values())}" for b, p in buckets.items())
            print(f"true field, stride {stride}: xy/rot/z {cells}")
    grads = identity_gradients(held, config)
    print(
        "median |d part / d own raw outputs| at the identity update: "
        + ", ".join(f"{k} {v:.3f}" for k, v in grads.items())
    )
    for design in args.designs:
        result = train_design(design, config, train, held, args)
        suffix = ("" if args.rot_weight == 1.0 else f"_rot{args.rot_weight:g}") + (f"_{args.tag}" if args.tag else "")
        (out / f"result_{design}{suffix}.json").write_text(json.dumps(result, indent=1))
    for i, path in enumerate(args.weights):
        result = judge_weights(path, config, held)
        (out / f"result_weights{i:02d}.json").write_text(json.dumps(result, indent=1))
    if args.designs or args.weights:
        report(out)
    return 0


if __name__ == "__main__":
    sys.exit(run_reporting_errors(main, "denoiser_designs.py"))
