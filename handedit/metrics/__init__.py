"""The HandEdit metric suite (paper sec. "Evaluation Metrics"): pure functions on arrays.

- ``similarity``: PSNR, SSIM (full / background outside M / ROI crop), region helpers.
- ``lpips``: LPIPS arithmetic on the features of an ONNX backbone + linear heads.
- ``frechet``: the Frechet distance behind FID.
- ``embodied``: Removal, Struct fidelity, ID fidelity (CLIP + Lab), Interaction.
- ``vlm``: the VLM judge (SC/PQ prompts, parsing, aggregation, cached HTTP client).
- ``human``: Krippendorff's alpha (ordinal), ICC(2,k), Fleiss' kappa, pairwise agreement.
- ``encoders``: onnxruntime wrappers for DINOv2, CLIP, LPIPS and Inception (user files).
- ``suite``: one item's full metric record (what the evaluate flow runs per item).

Nothing here imports Prefect; the evaluate flow (``flows/evaluate.py``) orchestrates.
"""
