"""`python -m pipeline.inspect RUN_ID`: one eval run's episodes beside the golden answers (``--labels``: the
job's model graded on every line of the golden answers)."""

import sys

from pipeline.report.answers import main

if __name__ == "__main__":
    sys.exit(main())
