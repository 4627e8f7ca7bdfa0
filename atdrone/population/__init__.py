"""Population algorithms (sp, br, pbt, hola, hola_no_g) as a table, and the pure maths beside them."""
