"""Evaluation: trajectories (ATE/RPE), images (PSNR/SSIM/depth L1/LPIPS), semantics (mIoU) and loop detection.

Ground-truth poses may be read here (and by the dataset players) only.
"""
