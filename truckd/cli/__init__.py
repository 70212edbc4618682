"""Command line: one small module per subcommand, calling the library only."""
