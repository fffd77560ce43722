"""What a validation run found, as records, and the files that hold them.

The stages build the records; checks decide their outcomes; the report reads
them. They import nothing of the pipeline. Only this package turns them into
files and back:

* records (kw-only dataclasses): :mod:`.common` (outcomes, a check),
  :mod:`.scene`, :mod:`.speed`, :mod:`.axis`, :mod:`.quadrature`, :mod:`.learning` (a scene
  comparison),
  :mod:`.cases` (the failures group), :mod:`.run` (the whole run, versions);
* :mod:`.json_io` — ``results.json`` both ways, and ``schema.json``;
* :mod:`.tables` — ``results.csv``, ``summary.md``, JUnit XML;
* :mod:`.layout` — every path of a run directory.

Everything is re-exported here: ``results.load(run_dir)``, ``results.Check``.
"""

from .axis import (AxisBudget, AxisCrossing, AxisModel, AxisPoint, BudgetAxis,  # noqa: F401
                   seconds_text)
from .cases import (BatchTest, CaseReference, CaseResult, CaseRow, Percentiles,  # noqa: F401
                    SppToMatch, SunSplit, Sweep, SweepRow, TailNumbers)
from .common import OUTCOMES, Check, ReferenceSummary, having  # noqa: F401
from .json_io import (SCHEMA_FILE, NoResultsError, ResultsError, from_json, load,  # noqa: F401
                      to_json, write_json)
from .learning import Learning, LearningPoint  # noqa: F401
from .quadrature import (BiasAtN, Calibration, EqualRays, GlossySettings,  # noqa: F401
                         Quadrature, SettingScore, Settings)
from .run import MINOR_VERSION, SCHEMA, VERSION, EstimatorInfo, Results  # noqa: F401
from .scene import (Convergence, EstimatorResult, RunStats, SceneResult,  # noqa: F401
                    Unbiasedness)
from .speed import (KINDS, Budget, BudgetRun, CostModel, Interval, Placement, Ratio,  # noqa: F401
                    Speed, Try)
from .tables import (CSV_FIELDS, counts_line, kinds_shown, learning_summary,  # noqa: F401
                     quadrature_summary, ranking_text, ratio_text, relmse_text, speed_summary,
                     summary, wall_text, write_csv, write_junit, write_summary)
