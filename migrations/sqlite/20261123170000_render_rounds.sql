-- Adaptive render phases (time_budget_s / target_rel_mse jobs): tasks come in rounds of
-- samples_per_task over all tiles; the coordinator checks each completed round in order and
-- stops after the first that meets the budget or target (later tasks become `skipped`).
-- Kept column-for-column in step with ../postgres. Never edit an applied migration.

-- Last round checked (−1: none yet).
ALTER TABLE phases ADD COLUMN rounds_checked BIGINT NOT NULL DEFAULT -1;
-- The round after which the phase stopped, if it stopped early.
ALTER TABLE phases ADD COLUMN stop_round BIGINT;
