"""imugraph.factors"""
