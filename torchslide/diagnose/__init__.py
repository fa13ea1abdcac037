"""Missing-physics diagnosis: one idea per module.

* candidates: the library of candidate terms (each nested: its switch at 0 gives the baseline)

* evaluator: DiagnosisEvaluator (scalar + vector observations, flattened likelihood)
* model_error: the grid's approximation error (runs on finer cells) as a model-error term of the
  likelihood (optional, Budgets.model_error_runs)
* predictive: posterior samples and posterior-predictive runs
* localise: standardised residuals, p-values, Getis-Ord map clusters (permutation + BH FDR), gauge windows
* screen: one-batch finite-difference screening with the baseline directions projected out
* power: the smallest switch of each candidate the recordings reveal, predicted and measured on the solver
* local: least squares on the solver, Laplace evidence, switch information (the local path's maths)
* local_path: the local path's models: baseline and candidate fits, path choice, likelihood ratio, profile
* lockstep: several fits advanced together, their solver runs merged into one batched call per round
* refit: calibration in the enlarged (baseline + switch) space
* verify: checks with solver runs: verified (importance-weighted) evidence, WAIC, Savage-Dickey,
  located mismatches re-scored after a refit
* decide: thresholds (set on null data) and the verdict
* pipeline: diagnose() -> Diagnosis
* report: report.json, report.md and figures
"""
from .decide import Thresholds, decide
from .evaluator import DiagnosisEvaluator
from .pipeline import Budgets, Diagnosis, check_budgets, check_candidates, diagnose

__all__ = ["DiagnosisEvaluator", "Budgets", "Diagnosis", "Thresholds", "decide", "diagnose", "check_budgets", "check_candidates"]
