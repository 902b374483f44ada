"""``ddp suite``: tasks x methods x seeds from one YAML file, resumable, aggregated like the paper's Table 1."""

from ddp.suite.budget import SuiteTimeLimit
from ddp.suite.report import aggregate, write_suite_report
from ddp.suite.runner import SuiteRunsFailed, execute_run, run_suite
from ddp.suite.spec import RunSpec, SuiteSpec, load_suite, select
from ddp.suite.store import ResultStore

__all__ = ["RunSpec", "SuiteSpec", "SuiteRunsFailed", "SuiteTimeLimit", "load_suite", "select", "ResultStore", "execute_run", "run_suite",
           "aggregate", "write_suite_report"]
