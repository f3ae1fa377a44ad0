# Record -> replay per configuration -> analysis -> replay tables (issue: same-observation replay).
