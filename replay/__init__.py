"""retargetd.replay: see README.md ("Layout") for its role."""

if __name__ != "retargetd.replay":
    raise ImportError(
        "import as retargetd.replay (pip install -e .), not as 'replay': "
        "the bare name would be this repository's folder, shadowing any PyPI "
        "package of that name"
    )
