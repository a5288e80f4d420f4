"""``python -m flyknot_tools.rope_study``: print the rope-model comparison table."""

from flyknot_tools.rope_study.cli import main

main()
