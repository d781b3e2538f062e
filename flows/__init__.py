"""Prefect flows (the DAGs): curate. Release and evaluate flows build on the same store."""
