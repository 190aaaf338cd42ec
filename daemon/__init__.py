"""retargetd.daemon — see README.md and ../shared/DESIGN.md for its role."""

if __name__ != "retargetd.daemon":
    raise ImportError(
        "import as retargetd.daemon (pip install -e .), not as 'daemon': a top-level 'daemon' "
        "would be this repository folder shadowing an unrelated PyPI package"
    )
