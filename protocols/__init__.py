"""retargetd.protocols — see README.md and ../shared/DESIGN.md for its role."""

if __name__ != "retargetd.protocols":
    raise ImportError(
        "import as retargetd.protocols (pip install -e .), not as 'protocols': a top-level 'protocols' "
        "would be this repository folder shadowing an unrelated PyPI package"
    )
