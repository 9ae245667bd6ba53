"""A policy controller across randomized worlds: what `batchsim evaluate` runs and reports.

    episodes.py     the episodes, each world commanded with its own seeded draw, measured
    commands.py     each world's command (a counter-based draw) and its distance from it
    report.py       the table, the JSON file and the plot
    policy_file.py  a controllers YAML's policy block, read without running it (the training's)
"""
