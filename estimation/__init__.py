"""estimation: the shared PoseGraph, estimators and consistency tools."""
