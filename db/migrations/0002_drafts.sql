-- CortexFuse case store, schema version 2: drafts (issue 7, 7.47 "nothing entered is lost").
-- Unsaved edits of a screen (kind 'marks': Photo & marks' landmarks and ROI) kept by the daemon
-- per case and per owner ('kiosk' for the cart's own browser, 'user:ID' for a logged-in user),
-- so that a restart of the browser itself does not lose them. A draft is NOT a revision: one
-- row per (case, kind, owner), replaced by each keep and removed when the edit is saved or
-- dropped; it is not exported with the case. Audited once when kept (draft.keep) and once when
-- dropped (draft.drop), never per update.
CREATE TABLE drafts (
  case_id     INTEGER NOT NULL REFERENCES cases(id),
  kind        TEXT NOT NULL CHECK (kind IN ('marks')),
  owner       TEXT NOT NULL CHECK (length(owner) BETWEEN 1 AND 80),
  user_id     INTEGER,                 -- users.id of a logged-in owner (no foreign key, like audit_log)
  body_json   TEXT NOT NULL CHECK (json_valid(body_json) AND length(body_json) <= 524288),
  saved_utc   TEXT NOT NULL,           -- when the client made the edit (its clock)
  updated_utc TEXT NOT NULL,           -- when the store kept it (the daemon's clock)
  PRIMARY KEY (case_id, kind, owner)
);
