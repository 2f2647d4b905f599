"""Run by Python at start-up in the processes that tests start with this folder on ``PYTHONPATH``: with
``PANOGS_TEST_PIPELINE=<module>`` set, their service and worker run that test double instead of the core's pipeline
(pipeline_stand_in.py). Does nothing otherwise. A test helper, not shipped.
"""

import os

if os.environ.get("PANOGS_TEST_PIPELINE"):
    import pipeline_stand_in

    pipeline_stand_in.replace_on_import(os.environ["PANOGS_TEST_PIPELINE"])
