"""`afm`: the project's command line (ros2cli is not on PyPI, so we bring our own).

Every subcommand has --help. Lengths accept units (500nm, 1.5um) or plain metres.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
from pathlib import Path

from afm_bringup.cli_batch import _add_batch
from afm_bringup.cli_calibrate import _add_calibrate
from afm_bringup.cli_errors import INPUT_STATUS, one_line, refuse
from afm_bringup.cli_map import _add_map
from afm_bringup.cli_scan import _add_scan
from afm_bringup.launcher import (
    GRAPH,
    NODES,
    Graph,
    check_no_restart_outputs,
    node_command,
    sim_calibration_file,
    with_sim_calibration,
)
from afm_bringup.units import (
    QuantityArgumentParser,
    angle_type,
    count_type,
    length_type,
    nm,
    positive_type,
)
from afm_core.recording.errors import recover_command


def _param(text):
    if ":=" not in text:
        raise argparse.ArgumentTypeError(f"parameter {text!r}: expected NAME:=VALUE")
    key, value = text.split(":=", 1)
    return key, value


# A push is a few scans, a localization and strokes: minutes on the simulator; an hour without
# a result is a hung nano-hand, not a slow push.
PUSH_TIMEOUT_S = 3600.0


def cmd_run(args):
    command = node_command(args.node, args.params_file, dict(args.param or []))
    os.execv(command[0], command)


def cmd_launch(args):
    nodes = args.nodes.split(",") if args.nodes else GRAPH
    unknown = [n for n in nodes if n not in NODES]
    if unknown:
        expected = f"expected names from {sorted(NODES)}"
        return refuse("launch", ValueError(f"--nodes {unknown}: {expected}"))
    overrides: dict[str, dict[str, str]] = {}
    for key, value in args.param or []:
        node, _, name = key.partition(".")
        if node not in nodes or not name:
            return refuse(
                "launch", ValueError(f"-p {key}: expected NODE.PARAMETER with NODE in {nodes}")
            )
        overrides.setdefault(node, {})[name] = value
    try:  # the folder before any node starts, which would log into it
        graph = Graph(args.log_dir, dict(os.environ))  # main() set the DDS environment
    except OSError as exc:
        reason = exc.strerror or exc
        return refuse("launch", ValueError(f"--log-dir {args.log_dir}: cannot use it: {reason}"))
    given = with_sim_calibration(nodes, overrides, sim_calibration_file())
    if given:
        print(
            f"afm launch: {', '.join(given)} use the simulator's calibration "
            f"({sim_calibration_file()}); -p NODE.calibration_file:=FILE for another",
            file=sys.stderr,
        )
    if args.record:
        from afm_core.recording import RecordingError
        from afm_core.recording.writer import check_output_path

        try:  # before any node starts: the recorder would refuse it only once the graph runs
            check_output_path(args.record)
            check_no_restart_outputs(args.record)
        except RecordingError as exc:
            print(f"afm launch: --record: {exc}", file=sys.stderr)
            return INPUT_STATUS
        graph.start("recorder", {"output": args.record})
        if "sim2real" in nodes:
            overrides.setdefault("sim2real", {}).setdefault("live_recording", args.record)
    for node in nodes:
        graph.start(node, overrides.get(node))
    if args.record:
        wait_for_recorder(graph)
    print(f"afm launch: ready: {', '.join(graph.processes)}; Ctrl-C stops them", file=sys.stderr)
    codes = graph.wait()
    failed = {n: c for n, c in codes.items() if c not in (0, -2)}
    return 1 if failed else 0


def wait_for_recorder(graph):
    """Tell the user 'ready' only once the recorder hears every topic that has a publisher."""
    import time

    from afm_bringup.commander import AfmCommander, AfmError
    from afm_ros import topics

    with AfmCommander("afm_launch_probe") as probe:
        time.sleep(1.0)  # let the nodes create their publishers
        try:
            probe.wait_until_subscribed(topics.RECORDED_BY_DEFAULT, timeout=20.0)
        except AfmError as exc:
            print(f"afm launch: warning: {exc}", file=sys.stderr)
        if graph.dead():
            print(f"afm launch: nodes exited during start-up: {graph.dead()}", file=sys.stderr)


def cmd_record(args):
    overrides = {"output": args.output, "compression": args.compression}
    if args.all:
        overrides["all_topics"] = "true"
    if args.topics:
        overrides["topics"] = "[" + ",".join(f"'{t}'" for t in args.topics) + "]"
    command = node_command("recorder", None, overrides)
    os.execv(command[0], command)


def cmd_replay(args):
    overrides = {
        "input": args.recording,
        "rate": repr(float(args.rate)),
        "loop": str(args.loop).lower(),
        "publish_clock": str(not args.no_clock).lower(),
        "wait_for_subscribers": str(args.wait_for_subscribers),
    }
    if args.topics:
        overrides["topics"] = "[" + ",".join(f"'{t}'" for t in args.topics) + "]"
    command = node_command("replay", None, overrides)
    os.execv(command[0], command)


def cmd_info(args):
    from afm_core.recording import RecordingError, RecordingReader

    try:
        with RecordingReader(args.recording) as reader:
            topics = reader.topics()
            size = reader.path.stat().st_size
            print(f"file:      {reader.path} ({size / 2**20:.2f} MiB)")
            print(f"duration:  {reader.duration_s:.3f} s")
            print(f"messages:  {reader.message_count}")
            print(f"topics:    {len(topics)}")
            width = max((len(t) for t in topics), default=5)
            for topic, info in topics.items():
                qos = info.offered_qos[0] if info.offered_qos else None
                qos_text = f"{qos.reliability}, {qos.durability}" if qos else "no QoS recorded"
                print(f"  {topic:<{width}}  {info.message_count:>7}  {info.type}  [{qos_text}]")
            damaged = reader.damaged_chunks()
            print(f"chunks:    {len(reader.summary.chunk_indexes)}, {len(damaged)} damaged (CRC)")
            for chunk in damaged:
                print(f"  {chunk}")
            sys.stdout.flush()  # a closed pipe shows here, not in the interpreter's exit
    except RecordingError as exc:
        print(f"afm info: {one_line(exc)}", file=sys.stderr)
        return INPUT_STATUS
    except BrokenPipeError:
        # the reader went away (`afm info F | head -1`): end quietly. cat, ls, grep and git are
        # killed by SIGPIPE there, and the shell reports 141 (128 + SIGPIPE); we return the
        # same, so `set -o pipefail` scripts see what they see with those tools. Writes to the
        # closed pipe at exit would fail again, so stdout goes to /dev/null.
        import signal

        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 128 + signal.SIGPIPE
    if damaged:  # damaged input: exit 2 like every other file command, the report above kept
        print(
            f"afm info: {recover_command(args.recording)} keeps the undamaged chunks",
            file=sys.stderr,
        )
        return INPUT_STATUS
    return 0


def cmd_recover(args):
    from afm_core.recording import RecordingError, recover

    try:
        recovery = recover(args.recording, args.output)
    except RecordingError as exc:
        print(f"afm recover: {exc}", file=sys.stderr)
        return 2
    for chunk in recovery.damaged:
        where = "" if chunk.offset >= 0 else " (file order)"
        print(f"skipped a damaged {chunk}{where}", file=sys.stderr)
    if recovery.orphaned:
        print(
            f"skipped {recovery.orphaned} messages whose channel was defined in a damaged chunk",
            file=sys.stderr,
        )
    if recovery.stopped:
        print(
            f"the file ends early or is unreadable after that: {recovery.stopped}", file=sys.stderr
        )
    print(f"recovered {recovery.messages} messages into {recovery.path}")
    return 0


def cmd_push(args):
    from afm_bringup.commander import AfmCommander, AfmError, ServerGone
    from afm_bringup.progress import Progress

    bar = Progress("push", "steps")

    def show(feedback):  # a bar of steps on a terminal; one line per step either way
        if bar.interactive:
            bar.update(feedback.step, feedback.steps_total, feedback.phase)
        bar.note(str(feedback))

    with AfmCommander() as afm, bar:
        try:
            job = afm.push(
                goal=args.goal,
                particle_id=args.particle,
                particle_position=args.at,
                strategy=args.strategy or "",  # "": the node's default
                tolerance=args.tolerance,
                feedback=show,
                wait=False,
                goal_angle=args.goal_angle,
            )
            try:
                result = job.result(args.timeout)
            except KeyboardInterrupt:
                print("cancelling the push ...", file=sys.stderr)
                job.cancel()
                result = job.result(30.0)
            except ServerGone:
                raise  # nobody left to cancel
            except AfmError:
                if not job.done():
                    try:  # a push we stop waiting for is stopped, not left running
                        job.cancel()
                    except AfmError:
                        pass
                raise
        except AfmError as exc:
            sys.exit(f"afm push: {exc}")
    outcome = f"{'succeeded' if result.success else result.verdict or 'failed'}: {result.message}"
    if not result.success and result.steps == 0:
        # refused or failed before any stroke: the result carries no position to report
        print(outcome)
        return 1
    print(
        f"{outcome}; particle at "
        f"({nm(result.achieved.x)}, {nm(result.achieved.y)}), error {nm(result.error)}"
        + (
            f", axis {math.degrees(result.achieved_angle):.2f} deg, error "
            f"{math.degrees(result.angle_error):.2f} deg"
            if math.isfinite(result.angle_error)
            else ""
        )
    )
    return 0 if result.success else 1


def cmd_sim2real(args):
    from afm_core.sim2real.diagnose import run_sim2real

    report = Path(args.report)
    if report.exists() and not report.is_dir():
        return refuse("sim2real", ValueError(f"--report {report}: a file; name a folder"))
    if report.exists() and any(report.iterdir()) and not args.overwrite:
        sys.exit(
            f"afm sim2real: --report {report} is not empty (use --overwrite to write into it)"
        )
    made_here = not report.exists()

    from afm_bringup.progress import Progress

    bar = Progress("sim2real", "steps")
    steps = [0]

    def progress(phase):  # the step now running; in a log (or with -v) one line per step
        steps[0] += 1
        if bar.interactive:
            bar.update(steps[0], None, phase[:60])
        if args.verbose or not bar.interactive:
            bar.note(f"  {phase}")

    try:
        with bar:
            diagnosis = run_sim2real(
                args.recording,
                args.model or None,
                report,
                progress=progress,
                effects=[e for e in args.effects.split(",") if e.strip()],
                missing_data="skip" if args.skip_incomplete else "error",
            )
    except (ValueError, OSError) as exc:  # the recording, the model or the folder
        return refuse("sim2real", exc)
    except RuntimeError as exc:
        sys.exit(f"afm sim2real: {exc}")
    except KeyboardInterrupt:
        if made_here and report.is_dir() and not any(report.iterdir()):
            report.rmdir()  # an empty folder would read as a report that found nothing
        raise
    print(f"verdict: {diagnosis.verdict}")
    print(diagnosis.summary())
    held = diagnosis.heldout
    if held.get("terms") and not diagnosis.chosen:  # a named term's are in the summary
        print(
            f"held-out operations ({', '.join(held['terms'])}, not named): chi2 "
            f"{held['chi2_before']:.1f} -> {held['chi2_after']:.1f} for {held['dof']} dof, "
            f"{100 * held['excess_reduction']:.0f} % of the excess over the noise removed"
        )
    print(
        f"report: {report / 'report.md'} (the verdict as JSON: {report / 'verdict.json'})"
        + (
            f"; updated simulator configuration: {report / 'updated_config.yaml'}"
            if (report / "updated_config.yaml").is_file()
            else ""
        )
    )
    return 0


def cmd_demo(args):
    from afm_bringup.demo import run_demo

    return run_demo(Path(args.output))


def _add_run(sub) -> None:
    p = sub.add_parser(
        "run",
        help="run one node in the foreground (like `ros2 run`)",
        description="Run one node with its default parameter file, plus overrides.",
    )
    p.add_argument("node", choices=sorted(NODES))
    p.add_argument("--params-file", help="YAML parameter file (default: the node's config/*.yaml)")
    p.add_argument(
        "-p",
        "--param",
        action="append",
        type=_param,
        metavar="NAME:=VALUE",
        help="override a parameter",
    )
    p.set_defaults(func=cmd_run)


def _add_launch(sub) -> None:
    p = sub.add_parser(
        "launch",
        help="start the whole graph as separate processes; Ctrl-C stops all",
        description="Start the graph's nodes as separate processes. Ctrl-C (or any node other "
        "than the recorder dying) stops them all, the recorder last; a dead recorder is reported "
        "and restarted on FILE.restartN.mcap (up to 3 times). The nodes die with the launcher, "
        "even when it is killed.",
    )
    p.add_argument("--nodes", help=f"comma-separated subset (default: {','.join(GRAPH)})")
    _add_exposure(p)
    p.add_argument(
        "--record", metavar="FILE.mcap", help="also record the default topics to this new file"
    )
    p.add_argument(
        "--log-dir", help="write each node's output to DIR/NODE.log instead of the terminal"
    )
    p.add_argument(
        "-p",
        "--param",
        action="append",
        type=_param,
        metavar="NODE.NAME:=VALUE",
        help="override a node parameter, e.g. -p driver.seed:=3",
    )
    p.set_defaults(func=cmd_launch)


def _add_exposure(p) -> None:
    p.add_argument(
        "--domain-id",
        type=int,
        default=None,
        metavar="N",
        help="ROS domain id for the graph (0-101; default: $ROS_DOMAIN_ID, else 0); the "
        "shells that talk to it need the same (export ROS_DOMAIN_ID=N)",
    )
    p.add_argument(
        "--network",
        choices=["localhost", "lab"],
        default="localhost",
        help="localhost (default): DDS on this machine only (UDP on 127.0.0.1); "
        "lab: discoverable on the subnet, for a lab network (pick a --domain-id)",
    )


def _add_record(sub) -> None:
    p = sub.add_parser(
        "record",
        help="record topics to a new MCAP file (Ctrl-C to finish)",
        description="Record topics to MCAP (ros2msg schemas, cdr messages, zstd chunks, indexed) "
        "that `ros2 bag play` and Foxglove open. Never overwrites a file.",
    )
    p.add_argument("-o", "--output", required=True, metavar="FILE.mcap")
    p.add_argument(
        "topics",
        nargs="*",
        help="topics (default: afm_bringup/config/recorder.yaml's: scans and maps with their "
        "images, lines, force traces, commands, poses, landmarks, tip shapes, paths, push goals, "
        "believed objects, teleop commands and status, markers, /tf, /tf_static, truth)",
    )
    p.add_argument("--all", action="store_true", help="record every topic that appears")
    p.add_argument(
        "--compression",
        default="zstd",
        choices=["zstd", "lz4", "none"],
        help="chunk compression (default zstd)",
    )
    p.set_defaults(func=cmd_record)


def _add_replay(sub) -> None:
    p = sub.add_parser(
        "replay",
        help="republish a recording with its original timing",
        description="Republish a recording with its original timing and QoS; publishes /clock "
        "so nodes with use_sim_time follow the recording's time.",
    )
    p.add_argument("recording")
    p.add_argument("--rate", type=float, default=1.0, help="speed factor (default 1.0)")
    p.add_argument("--topics", nargs="+", help="only these topics")
    p.add_argument("--loop", action="store_true", help="start over at the end")
    p.add_argument("--no-clock", action="store_true", help="do not publish /clock")
    p.add_argument(
        "--wait-for-subscribers",
        type=int,
        default=0,
        metavar="N",
        help="start only when every replayed topic has N subscribers (default 0: do not wait)",
    )
    p.set_defaults(func=cmd_replay)


def _add_info(sub) -> None:
    p = sub.add_parser(
        "info", help="topics, types, counts and duration of a recording (no ROS needed)"
    )
    p.add_argument("recording")
    p.set_defaults(func=cmd_info)


def _add_recover(sub) -> None:
    p = sub.add_parser(
        "recover", help="save the complete part of an unfinished (.part) or truncated recording"
    )
    p.add_argument("recording")
    p.add_argument("-o", "--output", help="new file (default: NAME.recovered.mcap)")
    p.set_defaults(func=cmd_recover)


def _add_push(sub) -> None:
    p = sub.add_parser(
        "push",
        help="push a particle to a goal and print feedback (Ctrl-C cancels)",
        description="Send a PushParticle goal to the nano-hand executor and print each step.",
    )
    target = p.add_mutually_exclusive_group(required=True)
    target.add_argument(
        "--particle",
        type=count_type("particle", 0, 2**31 - 1),  # -1, the default, stands for --at
        default=-1,
        help="landmark id of the particle (see /afm/landmarks)",
    )
    target.add_argument(
        "--at",
        nargs=2,
        type=length_type("at"),
        metavar=("X", "Y"),
        help="the particle nearest this position in afm_task (m, or with a unit: 55um), within "
        "the nano-hand's match_radius (nano_hand.yaml)",
    )
    p.add_argument(
        "--goal",
        nargs=2,
        required=True,
        type=length_type("goal"),
        metavar=("X", "Y"),
        help="where the particle should end, afm_task (m, or with a unit: 54.7um)",
    )
    p.add_argument(
        "--strategy",
        choices=["closed_loop", "nano_hand", "center", "rod_hand"],
        help="how to push (default: the nano-hand node's, closed_loop, which observes the "
        "particle with local scan lines between legs and re-plans; nano_hand: the open-loop "
        "zigzag)",
    )
    p.add_argument(
        "--goal-angle",
        type=angle_type("goal-angle"),
        default=None,
        help="a tube or rod: its axis at the goal, afm_task (rad, or with a unit: 15deg; "
        "default: keep its orientation); refused for a sphere",
    )
    p.add_argument(
        "--tolerance",
        type=length_type("tolerance", positive=True),
        default=20e-9,
        help="success radius around the goal (m, or with a unit; default 20nm)",
    )
    p.add_argument(
        "--timeout",
        type=positive_type("timeout"),
        default=PUSH_TIMEOUT_S,
        help=f"s to wait for the result, then cancel (default {PUSH_TIMEOUT_S:.0f}); a "
        "nano-hand that stops answering ends the wait within a few seconds anyway",
    )
    p.set_defaults(func=cmd_push)


def _add_image(sub) -> None:
    p = sub.add_parser(
        "image",
        help="drift compensation, tip estimation, reconstruction, landmarks on files",
        description=(
            "Run the imaging algorithms on image files (.npz, .gwy, .npy, and vendors' "
            ".ibw, .jpk, .spm, .sxm, .stp, .top); no ROS needed."
        ),
    )
    from afm_core.imaging.cli import add_subcommands
    from afm_core.imaging.cli import run as run_image

    add_subcommands(p, length_type("length"))
    p.set_defaults(func=run_image)


def _add_sim2real(sub) -> None:
    p = sub.add_parser(
        "sim2real",
        help="where a recording and the simulator differ, which physics is missing, "
        "the fitted term and its held-out improvement",
        description="Re-run a recording's commands in the simulator (--model), compare every "
        "measurement against the noise model, rank candidate physics the model lacks "
        "by held-out evidence, fit the chosen term and write report.md, plots and (when a "
        "term is named) updated_config.yaml into --report, and the verdict as verdict.json. The "
        "verdict: named, partly explained, not explained by the library, or no missing "
        "physics. Our recorder's "
        "files and rosbag2 MCAP both work; no ROS needed.",
    )
    p.add_argument(
        "recording", help="MCAP recording (needs /afm/tip_command and the measurements)"
    )
    p.add_argument(
        "--model",
        default="",
        help="simulator configuration YAML (default: the simulator's defaults)",
    )
    p.add_argument("--report", required=True, help="folder for the report (created)")
    p.add_argument(
        "--effects",
        default="",
        metavar="NAME,NAME",
        help="consider only these library terms, e.g. tip_radius,tip_wear (default: all of them; "
        "fewer terms run faster)",
    )
    p.add_argument(
        "--overwrite",
        action="store_true",
        help="write into a non-empty report folder (an earlier report's files are removed, "
        "other files kept)",
    )
    p.add_argument(
        "--skip-incomplete",
        action="store_true",
        help="leave out commands whose measurement is not in the file, and measurements no "
        "command claims (a recording cut short, a recovered .part, a restarted recorder's "
        "NAME.restartN.mcap, which starts with the latched commands of the session before it)",
    )
    p.add_argument(
        "--verbose",
        "-v",
        action="store_true",
        help="print each analysis step on its own line also on a terminal (where a progress "
        "bar shows the step now running; in a log every step gets a line anyway)",
    )
    p.set_defaults(func=cmd_sim2real)


def _add_demo(sub) -> None:
    p = sub.add_parser(
        "demo",
        help="the main job: run the graph end to end and write a report",
        description="Start the graph on the simulated instrument, do what the graph can do, "
        "record to MCAP, replay, evaluate offline and write an HTML report.",
    )
    p.add_argument(
        "--output",
        default="demo_output",
        help="folder for runs (default demo_output; each run gets a new subfolder)",
    )
    p.set_defaults(func=cmd_demo)


def build_parser() -> argparse.ArgumentParser:
    parser = QuantityArgumentParser(
        prog="afm",
        description="Run, drive, record and replay the AFM nano-manipulation graph.",
        epilog="Lengths accept units (500nm, 1.5um) or plain metres. "
        "Run `afm COMMAND --help` for details.",
    )
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    # one parser per subcommand, in the order `afm --help` lists them
    for add in (
        _add_run,
        _add_launch,
        _add_record,
        _add_replay,
        _add_info,
        _add_recover,
        _add_scan,
        _add_push,
        _add_image,
        _add_map,
        _add_calibrate,
        _add_sim2real,
        _add_batch,
        _add_demo,
    ):
        add(sub)
    return parser


# the subcommands that read files a user names; a damaged or wrong file is refused with one line
# and exit status 2 (argparse's status for bad input), never a traceback
FILE_COMMANDS = ("info", "recover", "image", "calibrate", "sim2real")


def input_errors() -> tuple[type[BaseException], ...]:
    """What the file readers (numpy, zipfile, gwyfile, yaml, mcap) may raise on damaged input
    that the core's own checks have not turned into ValueError or RecordingError."""
    import struct
    import tokenize
    import zipfile
    import zlib

    import yaml
    from mcap.exceptions import McapError

    from afm_core.recording import RecordingError

    return (
        ValueError,
        OSError,
        EOFError,
        KeyError,
        IndexError,
        TypeError,
        MemoryError,
        OverflowError,
        struct.error,
        zlib.error,
        zipfile.BadZipFile,
        tokenize.TokenError,
        yaml.YAMLError,  # a recording's QoS metadata
        McapError,
        RecordingError,
    )


# the subcommands that start ROS participants, here or in the processes they exec
ROS_COMMANDS = ("run", "launch", "record", "replay", "scan", "push", "demo")


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    if args.command in ROS_COMMANDS:
        from afm_ros import exposure

        try:
            exposure.apply(
                os.environ,
                domain_id=getattr(args, "domain_id", None),
                network=getattr(args, "network", "localhost"),
            )
        except ValueError as exc:
            print(f"afm {args.command}: {exc}", file=sys.stderr)
            return INPUT_STATUS
    try:
        return args.func(args) or 0
    except KeyboardInterrupt:  # Ctrl-C where a command keeps nothing: one line, no traceback
        print(f"afm {args.command}: interrupted", file=sys.stderr)
        return 130
    except Exception as exc:
        if args.command in FILE_COMMANDS and isinstance(exc, input_errors()):
            return refuse(args.command, exc)
        raise


if __name__ == "__main__":
    sys.exit(main())
