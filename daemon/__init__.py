"""retargetd.daemon: see README.md ("Layout") for its role."""

if __name__ != "retargetd.daemon":
    raise ImportError(
        "import as retargetd.daemon (pip install -e .), not as 'daemon': "
        "the bare name would be this repository's folder, shadowing any PyPI "
        "package of that name"
    )
