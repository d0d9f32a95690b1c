"""How good a density is: image metrics (PSNR, SSIM) and scores of rendered views against
the captured ones."""
