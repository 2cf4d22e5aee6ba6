"""Readers and writers of JWST NIRISS AMI files and of amigo's own products."""
