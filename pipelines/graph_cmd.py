"""`octofactor graph info|convert|optimize`: pose-graph files (.graph, .g2o, TUM .txt)."""
from __future__ import annotations

import sys

from pipelines.cli_common import add_output, output_of


def register(add_command) -> None:
    info = add_command("info", "summarise a pose-graph file (.graph, .g2o, TUM .txt)",
                       group="graph")
    info.add_argument("file")
    info.set_defaults(func=run_info)

    convert = add_command("convert", "convert between .graph, .g2o, TUM .txt and KITTI .kitti",
                          group="graph")
    convert.add_argument("input", metavar="SOURCE")
    add_output(convert, "the converted file (.graph, .g2o, TUM .txt, KITTI .kitti)",
               old_positional=True)
    convert.add_argument("--clouds", metavar="DIR",
                         help="attach per-node clouds DIR/<id>.xyz|.ply|.pcd (sensor frame)")
    convert.set_defaults(func=run_convert)

    optimize = add_command("optimize", "optimise a pose graph (Levenberg-Marquardt or iSAM2)",
                           group="graph")
    optimize.add_argument("input", metavar="SOURCE")
    add_output(optimize, "the optimised graph (.graph, .g2o, TUM .txt, KITTI .kitti)",
               old_positional=True)
    optimize.add_argument("--method", choices=("lm", "isam2"), default="lm")
    optimize.add_argument("--max-iterations", type=int, default=100)
    optimize.set_defaults(func=run_optimize)


def run_info(args) -> int:
    from estimation.io import format_of, read_pose_graph

    graph = read_pose_graph(args.file)
    stamps = graph.timestamps()
    counts = graph.factor_counts()
    print(f"file:    {args.file} ({format_of(args.file)})")
    print(f"nodes:   {len(graph.nodes)}")
    kinds = ", ".join(f"{kind} {n}" for kind, n in sorted(counts.items())) or "none"
    print(f"factors: {len(graph.factors)} ({kinds})")
    n_scans = sum(node.scan is not None for node in graph.nodes.values())
    print(f"points:  {graph.num_points()} in {n_scans} scans")
    if graph.timestamps_missing is not None:
        print("time:    unknown (the file has no timestamps)")
    elif len(stamps):
        first, last = float(stamps.min()), float(stamps.max())
        print(f"time:    {first!r} .. {last!r} ({last - first:.6f} s)")
    return 0


def _report_dropped(dropped: list[str], output: str) -> None:
    if dropped:
        print(f"octofactor: note: {output} cannot hold: {', '.join(dropped)} (dropped)",
              file=sys.stderr)


def run_convert(args) -> int:
    from estimation.io import load_node_clouds, read_pose_graph, write_pose_graph
    from pipelines.validate import output_file, output_path

    output_file("-o", output_path(args))
    graph = read_pose_graph(args.input)
    if args.clouds:
        attached = load_node_clouds(graph, args.clouds)
        print(f"attached clouds to {attached} of {len(graph.nodes)} nodes", file=sys.stderr)
    output = output_of(args)
    _report_dropped(write_pose_graph(output, graph), output)
    return 0


def run_optimize(args) -> int:
    from estimation.io import read_pose_graph, write_pose_graph
    from estimation.pose_graph import GAUGE_SIGMA
    from pipelines.validate import integer, output_file, output_path

    integer("--max-iterations", args.max_iterations, 1, 100000)
    output_file("-o", output_path(args))

    graph = read_pose_graph(args.input)
    if not graph.factors:
        print("octofactor: note: the graph has no factors; nothing to optimise", file=sys.stderr)
    # GTSAM failures arrive as one-line EstimationErrors (cli.main prints them, exit 2).
    result = graph.optimize(method=args.method, max_iterations=args.max_iterations)
    anchored = result.anchored_nodes
    if len(anchored) == 1:
        print(f"octofactor: note: the graph has no prior: node {anchored[0]} is "
              f"anchored at its initial pose by a weak prior (sigma {GAUGE_SIGMA:g} rad, "
              f"{GAUGE_SIGMA:g} m) to fix the gauge", file=sys.stderr)
    elif anchored:
        shown = ", ".join(str(i) for i in anchored[:10]) + (", ..." if len(anchored) > 10 else "")
        print(f"octofactor: note: the graph has {len(anchored)} unconnected parts without a "
              f"prior: nodes {shown} are anchored at their initial poses by weak priors "
              f"(sigma {GAUGE_SIGMA:g} rad, {GAUGE_SIGMA:g} m) to fix their gauges",
              file=sys.stderr)
    print(f"initial error: {result.initial_error:.10g}")
    print(f"final error:   {result.final_error:.10g} "
          f"({result.iterations} iterations, {result.method})")
    output = output_of(args)
    _report_dropped(write_pose_graph(output, graph), output)
    return 0
