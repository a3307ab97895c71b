"""`octofactor plugins`: the estimators installed (built-ins and entry points)."""
from __future__ import annotations


def register(add_command) -> None:
    parser = add_command("plugins", "list the estimators installed (entry-point group "
                         "octofactor.estimators) and the built-ins")
    parser.add_argument("--kind", choices=("filter", "registration"))
    parser.set_defaults(func=run)


def run(args) -> int:
    import warnings

    from estimation.plugins import PluginWarning, available_estimators

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", PluginWarning)
        estimators = available_estimators(args.kind)
    print(f"{'name':<22} {'kind':<13} source")
    for name, info in sorted(estimators.items()):
        print(f"{name:<22} {info.kind:<13} {info.source}")
    import sys

    for warning in caught:
        if issubclass(warning.category, PluginWarning):
            print(f"octofactor: warning: {warning.message}", file=sys.stderr)
    return 0
