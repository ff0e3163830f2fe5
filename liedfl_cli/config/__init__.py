"""Configs into objects: the config resolvers and schema checks, preflight, model and dataset building,
run folders and the data a run is rolled out on, parameter recovery."""
