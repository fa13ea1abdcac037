"""Missing-physics diagnosis (see /work/shared/DIAGNOSIS.md): one idea per module.

* evaluator: DiagnosisEvaluator (scalar + vector observations, flattened likelihood)
* predictive: posterior samples and posterior-predictive runs
* localise: standardised residuals, p-values, Getis-Ord map clusters (permutation + BH FDR), gauge windows
* screen: one-batch finite-difference screening with the baseline directions projected out
* refit: calibration in the enlarged (baseline + switch) space
* decide: thresholds and the verdict
* pipeline: diagnose() -> Diagnosis
* report: report.json, report.md and figures
"""
from .decide import Thresholds, decide
from .evaluator import DiagnosisEvaluator
from .pipeline import Budgets, Diagnosis, check_candidates, diagnose

__all__ = ["DiagnosisEvaluator", "Budgets", "Diagnosis", "Thresholds", "decide", "diagnose", "check_candidates"]
