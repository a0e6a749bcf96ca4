"""One module per `mmctl` command: ``add_arguments(parser)`` and ``run(args) -> int``."""
