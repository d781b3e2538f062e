"""What an operator watches: the release/QA page of a store (links to the Dask dashboard)."""
