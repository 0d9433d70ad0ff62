-- CortexFuse case store, schema version 1.
-- Times are UTC text, ISO 8601 with milliseconds: 2026-11-22T14:50:00.000Z (fixed width, so
-- they sort and compare as text). JSON columns hold strict JSON (json_valid is checked).
-- Blobs (volumes, photos, result files) live in blobs/ab/cdef... beside the database, named by
-- the SHA-256 of their content; rows hold the hash and size.

CREATE TABLE patients (
  id          INTEGER PRIMARY KEY,
  mrn         TEXT NOT NULL UNIQUE CHECK (length(mrn) BETWEEN 1 AND 64),
  family_name TEXT NOT NULL,
  given_name  TEXT NOT NULL DEFAULT '',
  birth_date  TEXT CHECK (birth_date IS NULL OR birth_date GLOB '[0-9][0-9][0-9][0-9]-[0-1][0-9]-[0-3][0-9]'),
  created_utc TEXT NOT NULL
);

CREATE TABLE cases (
  id          INTEGER PRIMARY KEY,
  uid         TEXT NOT NULL UNIQUE CHECK (length(uid) = 32),  -- random, kept across export/import
  patient_id  INTEGER REFERENCES patients(id),
  title       TEXT NOT NULL CHECK (length(title) BETWEEN 1 AND 200),
  state       TEXT NOT NULL DEFAULT 'new' CHECK (state IN ('new', 'planned', 'patient_registered',
                'photo_captured', 'landmarks', 'roi', 'registered', 'reviewed')),
  created_utc TEXT NOT NULL,
  updated_utc TEXT NOT NULL
);
CREATE INDEX cases_patient ON cases(patient_id);
CREATE INDEX cases_updated ON cases(updated_utc);

CREATE TABLE volumes (
  id            INTEGER PRIMARY KEY,
  case_id       INTEGER NOT NULL REFERENCES cases(id),
  modality      TEXT NOT NULL CHECK (modality IN ('T1', 'CT', 'fMRI', 'mask')),
  original_name TEXT NOT NULL,
  sha256        TEXT NOT NULL CHECK (length(sha256) = 64),
  size_bytes    INTEGER NOT NULL CHECK (size_bytes >= 0),
  created_utc   TEXT NOT NULL
);
CREATE INDEX volumes_case ON volumes(case_id);

CREATE TABLE photos (
  id              INTEGER PRIMARY KEY,
  case_id         INTEGER NOT NULL REFERENCES cases(id),
  original_name   TEXT NOT NULL,
  sha256          TEXT NOT NULL CHECK (length(sha256) = 64),
  size_bytes      INTEGER NOT NULL CHECK (size_bytes >= 0),
  intrinsics_json TEXT NOT NULL CHECK (json_valid(intrinsics_json)),  -- case-format.md "camera"
  created_utc     TEXT NOT NULL
);
CREATE INDEX photos_case ON photos(case_id);

-- Landmarks are revisioned: set_landmarks adds a revision, the old ones stay.
CREATE TABLE landmark_sets (
  id          INTEGER PRIMARY KEY,
  case_id     INTEGER NOT NULL REFERENCES cases(id),
  revision    INTEGER NOT NULL CHECK (revision >= 1),
  photo_id    INTEGER REFERENCES photos(id),
  created_utc TEXT NOT NULL,
  UNIQUE (case_id, revision)
);
CREATE TABLE landmarks (
  set_id   INTEGER NOT NULL REFERENCES landmark_sets(id),
  idx      INTEGER NOT NULL,
  name     TEXT NOT NULL,
  world_x_mm REAL NOT NULL, world_y_mm REAL NOT NULL, world_z_mm REAL NOT NULL,  -- LPS
  pixel_u  REAL NOT NULL, pixel_v REAL NOT NULL,                                 -- OpenCV pixels
  PRIMARY KEY (set_id, idx)
);

CREATE TABLE rois (
  id          INTEGER PRIMARY KEY,
  case_id     INTEGER NOT NULL REFERENCES cases(id),
  revision    INTEGER NOT NULL CHECK (revision >= 1),
  photo_id    INTEGER REFERENCES photos(id),
  roi_json    TEXT NOT NULL CHECK (json_valid(roi_json)),  -- case-format.md roi.json
  created_utc TEXT NOT NULL,
  UNIQUE (case_id, revision)
);

-- One row per registration run, with the parameters that produced it; a redo is a new row.
CREATE TABLE registrations (
  id                 INTEGER PRIMARY KEY,
  case_id            INTEGER NOT NULL REFERENCES cases(id),
  volume_id          INTEGER REFERENCES volumes(id),
  photo_id           INTEGER REFERENCES photos(id),
  landmark_set_id    INTEGER REFERENCES landmark_sets(id),
  roi_id             INTEGER REFERENCES rois(id),
  status             TEXT NOT NULL CHECK (status IN ('succeeded', 'failed', 'cancelled')),
  params_json        TEXT NOT NULL CHECK (json_valid(params_json)),   -- engine RegistrationParams
  initial_pose_json  TEXT CHECK (initial_pose_json IS NULL OR json_valid(initial_pose_json)),
  final_pose_json    TEXT CHECK (final_pose_json IS NULL OR json_valid(final_pose_json)),
  nmi                REAL,
  evaluations        INTEGER,
  seconds            REAL,
  stages_json        TEXT NOT NULL DEFAULT '[]' CHECK (json_valid(stages_json)),  -- per-stage timings
  error              TEXT,
  created_utc        TEXT NOT NULL
);
CREATE INDEX registrations_case ON registrations(case_id);

-- Result files (fused PNGs, meshes, ...), each with the parameters that produced it.
CREATE TABLE results (
  id              INTEGER PRIMARY KEY,
  case_id         INTEGER NOT NULL REFERENCES cases(id),
  registration_id INTEGER REFERENCES registrations(id),
  kind            TEXT NOT NULL CHECK (length(kind) BETWEEN 1 AND 64),
  name            TEXT NOT NULL,
  media_type      TEXT NOT NULL,
  sha256          TEXT NOT NULL CHECK (length(sha256) = 64),
  size_bytes      INTEGER NOT NULL CHECK (size_bytes >= 0),
  params_json     TEXT NOT NULL DEFAULT '{}' CHECK (json_valid(params_json)),
  created_utc     TEXT NOT NULL
);
CREATE INDEX results_case ON results(case_id);

CREATE TABLE users (
  id            INTEGER PRIMARY KEY,
  name          TEXT NOT NULL UNIQUE CHECK (length(name) BETWEEN 1 AND 64),
  role          TEXT NOT NULL CHECK (role IN ('surgeon', 'technician', 'reviewer', 'admin')),
  password_hash TEXT NOT NULL,  -- libsodium crypto_pwhash_str (argon2id)
  created_utc   TEXT NOT NULL,
  disabled      INTEGER NOT NULL DEFAULT 0 CHECK (disabled IN (0, 1))
);

CREATE TABLE sessions (
  id          INTEGER PRIMARY KEY,
  token_hash  TEXT NOT NULL UNIQUE,  -- BLAKE2b of the token; the token itself is never stored
  user_id     INTEGER NOT NULL REFERENCES users(id),
  created_utc TEXT NOT NULL,
  expires_utc TEXT NOT NULL,
  revoked     INTEGER NOT NULL DEFAULT 0 CHECK (revoked IN (0, 1))
);
CREATE INDEX sessions_user ON sessions(user_id);

-- Append-only: who viewed or changed what. The triggers refuse UPDATE and DELETE.
CREATE TABLE audit_log (
  id           INTEGER PRIMARY KEY,
  at_utc       TEXT NOT NULL,
  actor        TEXT NOT NULL,           -- user name, or 'kiosk' / 'system'
  user_id      INTEGER,                 -- no foreign key: the log outlives anything it names
  action       TEXT NOT NULL,
  case_id      INTEGER,
  details_json TEXT NOT NULL DEFAULT '{}' CHECK (json_valid(details_json))
);
CREATE INDEX audit_case ON audit_log(case_id);
CREATE TRIGGER audit_log_no_update BEFORE UPDATE ON audit_log
BEGIN SELECT RAISE(ABORT, 'audit_log is append-only: UPDATE refused'); END;
CREATE TRIGGER audit_log_no_delete BEFORE DELETE ON audit_log
BEGIN SELECT RAISE(ABORT, 'audit_log is append-only: DELETE refused'); END;

-- Results are kept: rows that record what was done are never changed or removed.
CREATE TRIGGER registrations_no_update BEFORE UPDATE ON registrations
BEGIN SELECT RAISE(ABORT, 'registrations are kept as recorded: UPDATE refused'); END;
CREATE TRIGGER registrations_no_delete BEFORE DELETE ON registrations
BEGIN SELECT RAISE(ABORT, 'registrations are kept as recorded: DELETE refused'); END;
CREATE TRIGGER results_no_update BEFORE UPDATE ON results
BEGIN SELECT RAISE(ABORT, 'results are kept as recorded: UPDATE refused'); END;
CREATE TRIGGER results_no_delete BEFORE DELETE ON results
BEGIN SELECT RAISE(ABORT, 'results are kept as recorded: DELETE refused'); END;
