"""retargetd.protocols: see README.md ("Layout") for its role."""

if __name__ != "retargetd.protocols":
    raise ImportError(
        "import as retargetd.protocols (pip install -e .), not as 'protocols': "
        "the bare name would be this repository's folder, shadowing any PyPI "
        "package of that name"
    )
