"""``retargetd.daemon.cli.main``: the ``retargetd`` command line: the entry point
(``main``), one module per subcommand, and the argument, take and rig helpers
several commands share.
"""
