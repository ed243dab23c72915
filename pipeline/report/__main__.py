"""`python -m pipeline.report`: build the report from the MLflow store."""

import sys

from pipeline.report.build import main

sys.exit(main())
