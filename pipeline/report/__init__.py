"""The report, from the MLflow store alone: loading, the paper's numbers, tables, Markdown, figures,
statistics, and the command lines `python -m pipeline.report` and `python -m pipeline.inspect`."""
