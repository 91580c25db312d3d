"""The paper's experiments regenerated with the SDK (``trafficrlhf experiment paper``).

- :func:`run_paper` + :class:`PaperConfig` (``config``): Tables 1-4 and Figure 3 of arXiv 2309.00709 on nuScenes
  val scenes, with stand-in annotators and learned reward models, each written as markdown, JSON and PNG;
- :mod:`~trafficrlhf_sdk.experiments.published`: what the paper publishes as far as a source shows it, and the
  direction its method claims for each metric;
- :mod:`~trafficrlhf_sdk.experiments.steps`: the resumable SDK stages the tables are made of.
"""

from trafficrlhf_sdk.experiments.config import GUIDANCES, TABLES, PaperConfig
from trafficrlhf_sdk.experiments.paper import run_paper
from trafficrlhf_sdk.experiments.published import EXPECTED, PUBLISHED, SOURCE, compare_change, published_change

__all__ = ["EXPECTED", "GUIDANCES", "PUBLISHED", "SOURCE", "TABLES", "PaperConfig", "compare_change",
           "published_change", "run_paper"]
