"""`disco train`: train a DiSCO model on KITTI-style sequences (or on scans without poses)."""

from __future__ import annotations

import shlex
from pathlib import Path
from typing import Annotated

import typer

from disco_cli.commands.options import (
    OxfordScaleOpt,
    PoseTopicOpt,
    ProtocolOpt,
    QuietOpt,
    ThreadsOpt,
    TopicOpt,
    output_option,
)
from disco_cli.runtime.console import fail, handle_errors, progress, stderr, warn


def _command_line(ctx: typer.Context, data: list[Path], output: Path) -> str:
    """The full command, every option spelled out (defaults too): the checkpoint's provenance."""
    words = ["disco", "train", *map(str, data), "-o", str(output)]
    for name, value in ctx.params.items():
        flag = "--" + name.replace("_", "-")
        if name in ("data", "output") or value is None:
            continue
        if name == "self_supervised":
            words += [flag] if value else []
        elif name in ("resume", "quiet"):
            continue  # resuming is recorded by chaining the commands; quiet changes nothing
        elif isinstance(value, bool):
            words.append(flag if value else f"--no-{name.replace('_', '-')}")
        elif isinstance(value, (list, tuple)):
            for v in value:
                words += [flag, str(v)]
        else:
            words += [flag, str(value)]
    return shlex.join(words)


@handle_errors
def train(
    ctx: typer.Context,
    data: Annotated[
        list[Path],
        typer.Argument(
            exists=True,
            show_default=False,
            help="Sequence folders (velodyne/ + poses.txt) or ROS bags, or folders of them "
            "(one world each).",
        ),
    ],
    output: Annotated[Path, output_option("Checkpoint to write (after every epoch).")],
    epochs: Annotated[int, typer.Option(min=1, help="Epochs to train.")] = 10,
    steps: Annotated[
        int, typer.Option(min=0, help="Steps per epoch (0: one pass over the queries).")
    ] = 0,
    batch: Annotated[int, typer.Option(min=1, max=4096, help="Quadruplets per step.")] = 8,
    negatives: Annotated[
        int, typer.Option(min=1, rich_help_panel="Samples", help="Negatives per quadruplet.")
    ] = 4,
    width: Annotated[
        int,
        typer.Option(
            min=2,
            rich_help_panel="Network",
            help="Channels of the U-Net's first block (paper: 64).",
        ),
    ] = 8,
    residual: Annotated[
        bool,
        typer.Option(
            rich_help_panel="Network",
            help="Add the U-Net to the BEV's height sum (start from `spectral`).",
        ),
    ] = True,
    bev_dropout: Annotated[
        float,
        typer.Option(
            rich_help_panel="Samples", help="Share of BEV cells dropped per sample (augmentation)."
        ),
    ] = 0.1,
    variants: Annotated[
        int,
        typer.Option(
            min=0,
            rich_help_panel="Samples",
            help="Augmented copies per scan made at load time: fewer beams, fewer points, "
            "a wedge occluded, tilted, shifted in z (needs poses).",
        ),
    ] = 0,
    augment_p: Annotated[
        float,
        typer.Option(
            min=0.0,
            max=1.0,
            rich_help_panel="Samples",
            help="Share of sampled scans shown as one of their copies.",
        ),
    ] = 0.5,
    occlude_p: Annotated[
        float,
        typer.Option(
            min=0.0,
            max=1.0,
            rich_help_panel="Samples",
            help="Share of BEVs that lose a 30-90 degree wedge.",
        ),
    ] = 0.0,
    lr: Annotated[float, typer.Option(rich_help_panel="Loss", help="Adam learning rate.")] = 1e-3,
    lambda_yaw: Annotated[
        float, typer.Option(rich_help_panel="Loss", help="Weight of the yaw KL loss.")
    ] = 0.1,
    lambda_verify: Annotated[
        float,
        typer.Option(
            rich_help_panel="Loss",
            help="Weight of the re-ranking loss (0: the paper's loss only; docs/training.md).",
        ),
    ] = 0.0,
    verify_candidates: Annotated[
        int,
        typer.Option(
            min=2, rich_help_panel="Loss", help="Re-ranking loss: scans of another pass per query."
        ),
    ] = 6,
    verify_radius: Annotated[
        float,
        typer.Option(
            rich_help_panel="Loss",
            help="Re-ranking loss: those scans lie within this distance (m).",
        ),
    ] = 10.0,
    d_pos: Annotated[
        float,
        typer.Option(rich_help_panel="Samples", help="Positives lie within this distance (m)."),
    ] = 3.0,
    d_neg: Annotated[
        float,
        typer.Option(rich_help_panel="Samples", help="Negatives lie beyond this distance (m)."),
    ] = 10.0,
    spacing: Annotated[
        float,
        typer.Option(
            rich_help_panel="Samples", help="Keep one scan per this much travel (m); 0: all."
        ),
    ] = 1.0,
    hard_after: Annotated[
        int,
        typer.Option(
            rich_help_panel="Samples",
            help="Epochs of random negatives before hard-negative mining.",
        ),
    ] = 2,
    self_supervised: Annotated[
        bool,
        typer.Option(
            "--self-supervised",
            rich_help_panel="Samples",
            help="No poses: positives are augmented copies of a scan.",
        ),
    ] = False,
    time_gap: Annotated[
        int,
        typer.Option(
            rich_help_panel="Samples",
            help="Self-supervised: negatives are at least this many frames apart.",
        ),
    ] = 50,
    val: Annotated[
        list[Path] | None,
        typer.Option(
            exists=True,
            file_okay=False,
            help="Held-out sequences for the per-epoch validation (repeatable).",
        ),
    ] = None,
    resume: Annotated[
        bool, typer.Option("--resume", help="Continue from the checkpoint at --output.")
    ] = False,
    device: Annotated[str, typer.Option(help="Torch device: cpu or cuda.")] = "cpu",
    seed: Annotated[
        int, typer.Option(min=0, help="Random seed (sampling, augmentation, initialization).")
    ] = 0,
    threads: ThreadsOpt = None,
    protocol: ProtocolOpt = None,
    oxford_scale: OxfordScaleOpt = None,
    topic: TopicOpt = None,
    pose_topic: PoseTopicOpt = None,
    quiet: QuietOpt = False,
) -> None:
    """Train the DiSCO U-Net (quadruplet + yaw loss) and write a checkpoint."""
    # deferred: loaded when the command runs, not at start-up (--help imports every command)
    from disco_cli.runtime.threads import set_threads

    threads = set_threads(threads)  # first: torch and BLAS read it as they load

    # deferred: torch and the training code (~2 s) load when the command runs, not for --help
    from disco_cli.io.output_paths import check_output_file
    from disco_cli.io.readers import oxford
    from disco_cli.model import check_device
    from disco_cli.model.bev import BEVConfig
    from disco_cli.training.data import load_training_data
    from disco_cli.training.loop import TrainOptions, resumable_checkpoint
    from disco_cli.training.loop import train as run_training

    check_device(device)
    if self_supervised and lambda_verify > 0:
        raise fail("--lambda-verify needs poses (other passes of a place); not --self-supervised")
    if self_supervised and variants > 0:
        raise fail("--variants needs poses; --self-supervised makes its own augmented copies")
    # Before any work: a checkpoint that cannot be written would lose every epoch.
    check_output_file(
        output,
        exists_ok=resume,
        what="the checkpoint",
        hint="pass --resume to continue it or choose another --output",
    )
    if protocol is not None:
        # The paper's training sessions and distances (disco_cli.evaluation.protocols) replace
        # DATA, --d-pos, --d-neg and --spacing (Oxford: --lambda-yaw too).
        from disco_cli.evaluation.protocols import training_setup  # deferred: --protocol only

        if len(data) != 1:
            raise fail("--protocol takes one dataset folder")
        setup = training_setup(protocol, data[0], warn)
        d_pos, d_neg, spacing = setup.d_pos, setup.d_neg, setup.spacing
        ctx.params.update(d_pos=d_pos, d_neg=d_neg, spacing=spacing)
        if setup.lambda_yaw is not None:
            source = ctx.get_parameter_source("lambda_yaw")
            given = getattr(source, "name", "") == "COMMANDLINE"
            if given and lambda_yaw != setup.lambda_yaw:
                raise fail(f"--lambda-yaw: --protocol {protocol} has no yaw to supervise")
            lambda_yaw = setup.lambda_yaw
            ctx.params["lambda_yaw"] = lambda_yaw
        if all(isinstance(s, Path) for s in setup.sessions):
            # The provenance records what the protocol chose, as a command that reruns it.
            data = setup.sessions
            ctx.params["protocol"] = None
        else:
            # A split of submaps, not folders: the command keeps --protocol to rerun it.
            ctx.params["oxford_scale"] = oxford_scale or oxford.DEFAULT_SCALE
        sessions = setup.sessions
    else:
        sessions = data
    command = _command_line(ctx, data, output)
    bev_config = BEVConfig()
    opts = TrainOptions(
        epochs=epochs,
        steps=steps,
        batch=batch,
        negatives=negatives,
        lr=lr,
        lambda_yaw=lambda_yaw,
        lambda_verify=lambda_verify,
        verify_candidates=verify_candidates,
        verify_radius=verify_radius,
        d_pos=d_pos,
        d_neg=d_neg,
        width=width,
        residual=residual,
        bev_dropout=bev_dropout,
        variants=variants,
        augment_p=augment_p if variants > 0 else 0.0,
        occlude_p=occlude_p,
        hard_after=hard_after,
        self_supervised=self_supervised,
        time_gap=time_gap,
        seed=seed,
        device=device,
    )
    if resume:  # a checkpoint that cannot be resumed is said before any data is loaded
        resumable_checkpoint(output, bev_config.heights, opts)

    def load(paths: list[Path], what: str, ss: bool, copies: int = 0):
        with progress(transient=True) as bar:
            task = bar.add_task(f"voxelizing {what}", total=None, rate="", unit="sequences")
            result = load_training_data(
                paths,
                bev_config,
                self_supervised=ss,
                spacing=0.0 if ss else spacing,
                seed=seed,
                threads=threads,
                variants=copies,
                on_progress=lambda done, total: bar.update(task, completed=done, total=total),
                topic=topic,
                pose_topic=pose_topic,
            )
        stderr.print(f"{what}: {len(result.anchors)} scans from {len(result.sessions)} sequences")
        return result

    with oxford.scale(oxford_scale):
        data_set = load(sessions, "training data", self_supervised, variants)
        val_set = load(val, "validation data", False) if val else None

    with progress() as bar:
        task = bar.add_task("training", total=None, rate="", unit="steps")

        def on_step(epoch: int, step: int, total: int, losses: dict[str, float]) -> None:
            text = " ".join(f"{k} {v:.3f}" for k, v in losses.items())
            bar.update(
                task,
                completed=step,
                total=total,
                description=f"epoch {epoch + 1}/{epochs}",
                rate=text,
                note=text,
            )

        run_training(
            data_set,
            bev_config,
            opts,
            output,
            command=command,
            resume=resume,
            val=val_set,
            on_step=on_step,
            log=lambda line: stderr.print(line, soft_wrap=True),
        )
    stderr.print(f"wrote {output}")
