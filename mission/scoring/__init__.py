"""How a mission is scored against ground truth: coverage, each step's judgement (collisions by
class, stuck steps, the decision-level measure), the study's metrics, what a mission records and
the run's report files."""
