-- CV phases (surrogate → train → render): what each phase needs and what its barrier made.
-- Kept column-for-column in step with ../postgres. Never edit an applied migration.

-- Samples per pixel the phase renders.
ALTER TABLE phases ADD COLUMN spp BIGINT NOT NULL DEFAULT 0;
-- Content address of the surrogate image a train phase weights its samples with.
ALTER TABLE phases ADD COLUMN surrogate TEXT;
-- Layout signature of the cell blocks accepted so far in a train phase (all must agree).
ALTER TABLE phases ADD COLUMN layout TEXT;
-- JSON of what the barrier after this phase computed (protocol::lease::BarrierStats).
ALTER TABLE phases ADD COLUMN barrier TEXT;
