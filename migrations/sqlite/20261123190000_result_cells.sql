-- The cell block of a `train` result is stored apart from its pixel frame: `data` keeps the
-- validated frame without cell blocks (what image assembly, convergence.csv and the round
-- checks read), `cells` the encoded training table (what the train barrier reads). Rows
-- written before this migration keep their cell blocks inside `data` and `cells` NULL.
-- Kept column-for-column in step with ../postgres. Never edit an applied migration.
ALTER TABLE results ADD COLUMN cells BLOB;
