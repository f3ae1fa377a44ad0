# Records -> verified manifest -> summary -> tables and figures (issue: regenerate the paper's tables).
