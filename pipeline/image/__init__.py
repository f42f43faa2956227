"""Whole-image operations before detection: stripe-noise removal and superpixel segmentation."""
