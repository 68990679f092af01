"""One module per ``jaxbvh`` subcommand: ``add_parser(subparsers)`` and ``run(args) -> dict``."""
