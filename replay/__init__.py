"""retargetd.replay — see README.md and ../shared/DESIGN.md for its role."""

if __name__ != "retargetd.replay":
    raise ImportError(
        "import as retargetd.replay (pip install -e .), not as 'replay': a top-level 'replay' "
        "would be this repository folder shadowing an unrelated PyPI package"
    )
