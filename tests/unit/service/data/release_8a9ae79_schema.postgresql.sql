-- the job database as dsareg 8a9ae79 created it (python -m tests.support.release_schema)

CREATE TABLE job_blobs (
	job_id VARCHAR(32) NOT NULL,
	sha256 VARCHAR(64) NOT NULL,
	role VARCHAR(32) NOT NULL
);

CREATE INDEX ix_job_blobs_job_id ON job_blobs (job_id);

CREATE INDEX ix_job_blobs_sha256 ON job_blobs (sha256);

CREATE TABLE job_callbacks (
	job_id VARCHAR(32) NOT NULL,
	url TEXT NOT NULL,
	delivery_id VARCHAR(32) NOT NULL,
	state VARCHAR(16) NOT NULL,
	attempts INTEGER NOT NULL,
	next_attempt_at FLOAT NOT NULL,
	lease_until FLOAT,
	last_attempt_at FLOAT,
	delivered_at FLOAT,
	last_status INTEGER,
	last_error TEXT,
	PRIMARY KEY (job_id)
);

CREATE INDEX ix_job_callbacks_state ON job_callbacks (state, next_attempt_at);

CREATE TABLE job_events (
	seq SERIAL NOT NULL,
	job_id VARCHAR(32) NOT NULL,
	at FLOAT NOT NULL,
	event VARCHAR(32) NOT NULL,
	worker_id VARCHAR(96),
	attempt INTEGER,
	detail TEXT,
	PRIMARY KEY (seq)
);

CREATE INDEX ix_job_events_job_id ON job_events (job_id);

CREATE TABLE job_exports (
	job_id VARCHAR(32) NOT NULL,
	target TEXT NOT NULL,
	state VARCHAR(16) NOT NULL,
	attempts INTEGER NOT NULL,
	next_attempt_at FLOAT NOT NULL,
	lease_until FLOAT,
	last_attempt_at FLOAT,
	done_at FLOAT,
	outcome TEXT,
	last_error TEXT,
	PRIMARY KEY (job_id)
);

CREATE INDEX ix_job_exports_state ON job_exports (state, next_attempt_at);

CREATE TABLE job_previous (
	job_id VARCHAR(32) NOT NULL,
	previous_id VARCHAR(32) NOT NULL,
	PRIMARY KEY (job_id)
);

CREATE TABLE jobs (
	id VARCHAR(32) NOT NULL,
	owner VARCHAR(64) NOT NULL,
	status VARCHAR(16) NOT NULL,
	created_at FLOAT NOT NULL,
	updated_at FLOAT NOT NULL,
	started_at FLOAT,
	finished_at FLOAT,
	attempts INTEGER NOT NULL,
	max_attempts INTEGER NOT NULL,
	worker_id VARCHAR(96),
	lease_expires_at FLOAT,
	cancel_requested BOOLEAN NOT NULL,
	options TEXT NOT NULL,
	geometry TEXT,
	inputs TEXT NOT NULL,
	progress TEXT,
	result TEXT,
	error TEXT,
	artifacts TEXT,
	warnings TEXT,
	idempotency_key VARCHAR(255),
	request_hash VARCHAR(64),
	input_bytes BIGINT NOT NULL,
	review_decision VARCHAR(16),
	review TEXT,
	PRIMARY KEY (id),
	CONSTRAINT uq_jobs_owner_idempotency UNIQUE (owner, idempotency_key)
);

CREATE INDEX ix_jobs_created ON jobs (created_at, id);

CREATE INDEX ix_jobs_status_created ON jobs (status, created_at);

CREATE TABLE store_probe (
	id SERIAL NOT NULL,
	at FLOAT NOT NULL,
	PRIMARY KEY (id)
);

CREATE TABLE workers (
	id VARCHAR(96) NOT NULL,
	pid INTEGER,
	last_seen FLOAT NOT NULL,
	PRIMARY KEY (id)
);

CREATE TABLE blob_data (
	sha256 VARCHAR(64) NOT NULL,
	size BIGINT NOT NULL,
	created_at FLOAT NOT NULL,
	data BYTEA NOT NULL,
	PRIMARY KEY (sha256)
);

CREATE TABLE dimse_instances (
	sop_instance_uid VARCHAR(64) NOT NULL,
	study_uid VARCHAR(64) NOT NULL,
	series_uid VARCHAR(64) NOT NULL,
	sop_class_uid VARCHAR(64) NOT NULL,
	sha256 VARCHAR(64) NOT NULL,
	size BIGINT NOT NULL,
	association VARCHAR(64) NOT NULL,
	calling_ae VARCHAR(16) NOT NULL,
	state VARCHAR(16) NOT NULL,
	received_at FLOAT NOT NULL,
	PRIMARY KEY (sop_instance_uid)
);

CREATE INDEX ix_dimse_instances_association ON dimse_instances (association);

CREATE INDEX ix_dimse_instances_study_uid ON dimse_instances (study_uid);

CREATE INDEX ix_dimse_state_study ON dimse_instances (state, study_uid);
