"""imugraph.io"""
