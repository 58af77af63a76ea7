"""fe_node package."""
