"""`python -m pipeline.lm.training --request request.json`: see `pipeline.lm.training.entry`."""

from pipeline.lm.training.entry import main

main()
