"""The paper's experiment (epochs x runs) with peers, its result files and its report."""
