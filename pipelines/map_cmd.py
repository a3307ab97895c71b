"""``octofactor map`` (fuse a scan graph into an octree) and ``octofactor octree info|convert|
export`` (inspect and convert .bt/.ot files). Heavy imports stay inside the run functions."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from pipelines.cli_common import add_output, output_of


def register(add_command) -> None:
    p = add_command("map", "fuse the scans of a .graph file into an octree (.bt or .ot), "
                    "byte-identical to graph2tree")
    p.add_argument("graph", help="pose graph: OctoMap .graph (poses + scans), or .g2o / TUM "
                   ".txt with --clouds")
    p.add_argument("--clouds", default=None, metavar="DIR",
                   help="per-node clouds DIR/<node_id>.xyz|.ply|.pcd in the sensor frame "
                   "(replace the graph's scans)")
    p.add_argument("-r", "--resolution", type=float, default=0.1, help="leaf size in m (0.1)")
    p.add_argument("--max-range", type=float, default=-1.0,
                   help="cut rays at this range in m (-1 = no limit, graph2tree -m)")
    p.add_argument("--discretize", action="store_true",
                   help="insert voxel centres of the endpoints (graph2tree -discretize)")
    p.add_argument("-o", "--output", required=True,
                   help="OUT.bt (max-likelihood, pruned) or OUT.ot (full log-odds, pruned)")
    p.set_defaults(func=run_map)

    p = add_command("info", "print size, leaves, bounds and memory of a .bt/.ot file",
                    group="octree")
    p.add_argument("file")
    p.set_defaults(func=run_info)

    p = add_command("convert", "convert between .bt and .ot (by extension)", group="octree")
    p.add_argument("input", metavar="SOURCE")
    add_output(p, "OUT.bt or OUT.ot", old_positional=True)
    p.set_defaults(func=run_convert)

    p = add_command("export", "export occupied voxels to .ply, or a height slice to .png",
                    group="octree")
    p.add_argument("file")
    p.add_argument("-o", "--output", required=True, help="OUT.ply or OUT.png")
    p.add_argument("--height", type=float, default=None,
                   help="slice height in m for .png (default: the middle of the map)")
    p.set_defaults(func=run_export)


def run(args: argparse.Namespace) -> int:
    return run_map(args)


def _check_ext(path: str, allowed: tuple[str, ...]) -> str:
    from estimation.errors import OctofactorError

    ext = Path(path).suffix.lower()
    if ext not in allowed:
        raise OctofactorError(f"{path}: extension must be one of {', '.join(allowed)}")
    return ext


def run_map(args: argparse.Namespace) -> int:
    from estimation.errors import OctofactorError
    from pipelines.validate import map_options

    _check_ext(args.output, (".bt", ".ot"))
    map_options(args)
    if args.clouds is None and Path(args.graph).suffix.lower() == ".graph":
        # the .graph records hold everything graph2tree uses: no PoseGraph, no GTSAM import
        from estimation.scan_graph import map_scan_graph_records
        from mapping.fusion import fuse_scan_records
        from pipelines.runtime import keep_freed_memory

        keep_freed_memory()
        try:
            records, _ = map_scan_graph_records(args.graph)
        except FileNotFoundError:
            raise OctofactorError(f"{args.graph}: no such file") from None
        if not any(record.n_points for record in records):
            raise OctofactorError(f"{args.graph}: no node has a scan (give --clouds DIR for "
                                  ".g2o/TUM graphs)")
        tree = fuse_scan_records(records, args.resolution, max_range=args.max_range,
                                 discretize=args.discretize, progress=sys.stderr.isatty())
    else:
        from estimation.io import load_node_clouds, read_pose_graph
        from mapping import fuse

        graph = read_pose_graph(args.graph)
        if args.clouds is not None:
            load_node_clouds(graph, args.clouds)
        if not any(n.scan is not None and len(n.scan.points) for n in graph.nodes.values()):
            raise OctofactorError(f"{args.graph}: no node has a scan (give --clouds DIR for "
                                  ".g2o/TUM graphs)")
        tree = fuse(graph, args.resolution, max_range=args.max_range,
                    discretize=args.discretize, progress=sys.stderr.isatty())
    tree.write(args.output)  # .bt or .ot by extension
    print(f"{args.output}: {tree.size()} nodes, {tree.num_leaf_nodes()} leaves, "
          f"resolution {args.resolution:g} m")
    return 0


def run_info(args: argparse.Namespace) -> int:
    from mapping import OcTree

    tree = OcTree.read(args.file)
    lo, hi = tree.metric_bounds()
    occ = tree.occupied_voxels()
    print(f"file: {args.file}")
    print(f"type: {getattr(tree, '_file_id', None) or tree.tree_type}")
    print(f"resolution: {tree.resolution:g} m")
    print(f"nodes: {tree.size()} ({tree.num_inner_nodes()} inner, {tree.num_leaf_nodes()} "
          f"leaves, {len(occ)} occupied)")
    print(f"bounds: [{lo[0]:.2f}, {lo[1]:.2f}, {lo[2]:.2f}] .. [{hi[0]:.2f}, {hi[1]:.2f}, "
          f"{hi[2]:.2f}] m")
    print(f"memory (liboctomap memoryUsage): {tree.memory_usage()} B")
    return 0


def run_convert(args: argparse.Namespace) -> int:
    from mapping import OcTree

    output = output_of(args)
    _check_ext(output, (".bt", ".ot"))
    tree = OcTree.read(args.input)
    tree.write(output)
    print(f"{output}: {tree.size()} nodes")
    return 0


def run_export(args: argparse.Namespace) -> int:
    from mapping import OcTree
    from mapping.export import save_height_slice, write_ply
    from pipelines.validate import number

    ext = _check_ext(args.output, (".ply", ".png"))
    number("--height", args.height, -1e30, 1e30, allow_none=True)
    tree = OcTree.read(args.file)
    if ext == ".ply":
        n = write_ply(tree, args.output)
        print(f"{args.output}: {n} occupied voxels")
    else:
        save_height_slice(tree, args.output, height=args.height)
        print(f"{args.output}: height slice")
    return 0
