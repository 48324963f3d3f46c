// dtraced's status page: jobs, workers and a live preview of one job, polled from the
// collector's /ui/api routes with the session cookie. No framework and no build step; the
// collector serves this file as is. The CSRF value lives in a variable only (never in storage).
'use strict';

(() => {
  const POLL_MS = 1000;
  const JOBS_LIMIT = 100;

  const $ = (id) => document.getElementById(id);
  const el = (tag, cls, text) => {
    const e = document.createElement(tag);
    if (cls) e.className = cls;
    if (text !== undefined) e.textContent = text;
    return e;
  };

  // ---- formatting (the viewer's locale) ----
  const numFmt = new Intl.NumberFormat(undefined, {maximumFractionDigits: 0});
  const oneFmt = new Intl.NumberFormat(undefined, {minimumFractionDigits: 1, maximumFractionDigits: 1});
  const twoFmt = new Intl.NumberFormat(undefined, {minimumFractionDigits: 2, maximumFractionDigits: 2});
  const relFmt = new Intl.RelativeTimeFormat(undefined, {numeric: 'auto', style: 'short'});
  const dateFmt = new Intl.DateTimeFormat(undefined, {dateStyle: 'medium', timeStyle: 'medium'});
  const durFmt = typeof Intl.DurationFormat === 'function'
    ? new Intl.DurationFormat(undefined, {style: 'narrow'}) : null;

  const zeroFmt = new Intl.NumberFormat(undefined, {style: 'unit', unit: 'second', unitDisplay: 'narrow'});

  function duration(s) {
    if (s === null || s === undefined || !Number.isFinite(s)) return '–';
    let t = Math.max(0, Math.round(s));
    if (t === 0) return zeroFmt.format(0);
    const h = Math.floor(t / 3600);
    t -= h * 3600;
    const m = Math.floor(t / 60);
    const sec = t - m * 60;
    if (durFmt) {
      const d = h > 0 ? {hours: h, minutes: m} : m > 0 ? {minutes: m, seconds: sec} : {seconds: sec};
      return durFmt.format(d);
    }
    return h > 0 ? `${h} h ${m} min` : m > 0 ? `${m} min ${sec} s` : `${sec} s`;
  }

  function ago(seconds) {
    const s = Math.max(0, seconds);
    if (s < 60) return relFmt.format(-Math.round(s), 'second');
    if (s < 3600) return relFmt.format(-Math.round(s / 60), 'minute');
    if (s < 86400) return relFmt.format(-Math.round(s / 3600), 'hour');
    return relFmt.format(-Math.round(s / 86400), 'day');
  }

  function setText(node, text) {
    if (node.textContent !== text) node.textContent = text;
  }
  function setTitle(node, text) {
    if (node.title !== text) node.title = text;
  }

  // ---- session and requests ----
  let csrf = null;        // in memory only
  let signedIn = false;
  let role = null;        // the session's role (GET /ui/session, the sign-in's answer)

  // A viewer's session watches: the collector refuses its state changes (403), so the page shows
  // none of the controls that make them (CSS .read-only .writer-only) and sends none.
  function readOnly() {
    return role === 'viewer';
  }

  function applyRole(r) {
    role = typeof r === 'string' ? r : null;
    document.body.classList.toggle('read-only', readOnly());
    $('role-note').hidden = !readOnly();
  }

  class Unauthorized extends Error {}
  class HttpError extends Error {
    constructor(status, message) {
      super(message);
      this.status = status;
    }
  }

  function showSignedOut(message) {
    signedIn = false;
    csrf = null;
    applyRole(null);
    stopPolling();
    $('app-view').hidden = true;
    $('signout').hidden = true;
    $('signin-view').hidden = false;
    setText($('signin-error'), message || '');
    setText($('conn'), '');
    resetJobs();
    resetWorkers();
    selectJob(null);
    $('token').focus();
  }

  function showSignedIn(sessionRole) {
    signedIn = true;
    applyRole(sessionRole);
    $('signin-view').hidden = true;
    $('app-view').hidden = false;
    $('signout').hidden = false;
    $('token').value = '';
    setText($('signin-error'), '');
    startPolling();
  }

  async function errorText(res) {
    try {
      const body = await res.json();
      if (body && typeof body.error === 'string') return body.error;
    } catch (e) { /* not JSON */ }
    return `HTTP ${res.status}`;
  }

  // A state-changing request with the session's CSRF value. Answers the parsed JSON (or null).
  async function post(path, body, method = 'POST') {
    const headers = {'X-Dtraced-CSRF': csrf || ''};
    const init = {method, headers, credentials: 'same-origin', cache: 'no-store'};
    if (body !== undefined) {
      headers['Content-Type'] = 'application/json';
      init.body = JSON.stringify(body);
    }
    const res = await fetch(path, init);
    if (res.status === 401) {
      showSignedOut('Your session has ended: sign in again.');
      throw new Unauthorized();
    }
    if (!res.ok) throw new Error(await errorText(res));
    if (res.status === 204) return null;
    const type = res.headers.get('Content-Type') || '';
    return type.includes('json') ? res.json() : null;
  }

  // A conditional GET: answers {status: 304} or {status: 200, etag, res}.
  async function get(path, etag) {
    const headers = {};
    if (etag) headers['If-None-Match'] = etag;
    const res = await fetch(path, {headers, credentials: 'same-origin', cache: 'no-store'});
    if (res.status === 401) {
      showSignedOut('Your session has ended: sign in again.');
      throw new Unauthorized();
    }
    if (res.status === 304) return {status: 304};
    if (!res.ok) throw new HttpError(res.status, await errorText(res));
    return {status: 200, etag: res.headers.get('ETag'), res};
  }

  $('signin-form').addEventListener('submit', async (ev) => {
    ev.preventDefault();
    const button = ev.target.querySelector('button');
    button.disabled = true;
    setText($('signin-error'), '');
    try {
      const res = await fetch('/ui/session', {
        method: 'POST', credentials: 'same-origin', cache: 'no-store',
        headers: {'Content-Type': 'application/json'},
        body: JSON.stringify({token: $('token').value.trim()}),
      });
      if (res.ok) {
        const answer = await res.json();
        csrf = answer.csrf;
        showSignedIn(answer.role);
      } else if (res.status === 401) {
        setText($('signin-error'), 'That token is not this farm\'s.');
      } else if (res.status === 429) {
        setText($('signin-error'), 'Too many failed sign-ins: wait a minute.');
      } else {
        setText($('signin-error'), await errorText(res));
      }
    } catch (e) {
      setText($('signin-error'), 'The collector does not answer.');
    } finally {
      button.disabled = false;
    }
  });

  $('signout').addEventListener('click', async () => {
    // No poll may reach the collector once the session is gone: it would be answered 401 (and
    // under load one in flight often was). Stop the pollers and let their steps finish first.
    stopPolling();
    await Promise.all(pollers.map((p) => p.quiet()));
    try {
      await fetch('/ui/session', {method: 'DELETE', credentials: 'same-origin',
                                  headers: {'X-Dtraced-CSRF': csrf || ''}});
    } catch (e) { /* signed out locally all the same */ }
    showSignedOut('Signed out.');
  });

  // ---- polling: one request in flight per resource, paused while the tab is hidden ----
  class Poller {
    constructor(name, step) {
      this.name = name;
      this.step = step;       // async () => delay in ms before the next step (0: at once)
      this.timer = null;
      this.running = false;
      this.busy = false;
      this.settled = Promise.resolve();  // resolves when the step in flight, if any, has ended
    }
    start() {
      this.running = true;
      this.kick(0);
    }
    stop() {
      this.running = false;
      clearTimeout(this.timer);
      this.timer = null;
    }
    kick(delay) {
      clearTimeout(this.timer);
      this.timer = null;
      if (!this.running || document.hidden) return;
      this.timer = setTimeout(() => this.run(), delay);
    }
    async run() {
      this.timer = null;
      if (this.busy || !this.running || document.hidden) return;
      this.busy = true;
      let ended;
      this.settled = new Promise((resolve) => { ended = resolve; });
      let next = POLL_MS;
      try {
        next = await this.step();
        markConnected(this.name, true);
      } catch (e) {
        if (e instanceof Unauthorized) return;
        markConnected(this.name, false, e.message);
      } finally {
        this.busy = false;
        ended();
      }
      this.kick(next);
    }
    // Resolves once no step of this poller is in flight.
    async quiet() {
      while (this.busy) await this.settled;
    }
  }

  const connErrors = new Map();
  function markConnected(name, ok, message) {
    if (ok) connErrors.delete(name); else connErrors.set(name, message);
    const conn = $('conn');
    if (!signedIn) return;
    if (connErrors.size === 0) {
      setText(conn, 'live');
      conn.classList.remove('bad');
    } else {
      setText(conn, `collector unreachable: ${[...connErrors.values()][0]}`);
      conn.classList.add('bad');
    }
  }

  const jobsPoller = new Poller('jobs', pollJobs);
  const workersPoller = new Poller('workers', pollWorkers);
  const tilesPoller = new Poller('tiles', pollTiles);
  const pollers = [jobsPoller, workersPoller, tilesPoller];

  function startPolling() {
    jobsPoller.start();
    workersPoller.start();
    if (preview.job !== null) tilesPoller.start();
  }
  function stopPolling() {
    for (const p of pollers) p.stop();
  }
  document.addEventListener('visibilitychange', () => {
    if (!signedIn) return;
    for (const p of pollers) if (p.running) p.kick(0);
  });

  // ---- jobs ----
  const jobRows = new Map();   // id -> {tr, cells..., job}
  let jobsEtag = null;

  function resetJobs() {
    jobsEtag = null;
    for (const r of jobRows.values()) r.tr.remove();
    jobRows.clear();
    $('jobs-empty').hidden = false;
  }

  function actionButton(label, cls, handler) {
    const b = el('button', cls, label);
    b.type = 'button';
    b.addEventListener('click', handler);
    return b;
  }

  function makeJobRow(id) {
    const tr = el('tr');
    tr.dataset.job = String(id);
    const r = {tr, job: null};
    r.id = el('td', 'num');
    r.output = el('td', 'opt ellipsis');
    r.state = el('td');
    r.stateBadge = el('span', 'badge');
    r.state.append(r.stateBadge);
    r.progress = el('td');
    const wrap = el('div', 'progress');
    r.bar = el('progress');
    r.bar.max = 1;
    r.bar.value = 0;
    r.tiles = el('span', 'tiles num');
    wrap.append(r.bar, r.tiles);
    r.progress.append(wrap);
    r.frames = el('td', 'opt num');
    r.elapsed = el('td', 'opt num');
    r.eta = el('td', 'num');
    r.spp = el('td', 'opt num');
    r.prio = el('td', 'num opt-narrow');
    r.prioForm = el('form', 'prio-form');
    r.prioInput = el('input');
    r.prioInput.type = 'number';
    r.prioInput.min = '-1000';
    r.prioInput.max = '1000';
    r.prioInput.step = '1';
    r.prioInput.setAttribute('aria-label', `Priority of job ${id}`);
    r.prioSet = el('button', 'small writer-only', 'Set');
    r.prioSet.type = 'submit';
    r.prioSet.setAttribute('aria-label', `Set the priority of job ${id}`);
    r.prioForm.append(r.prioInput, r.prioSet);
    r.prioForm.addEventListener('submit', (ev) => {
      ev.preventDefault();
      const p = Number(r.prioInput.value);
      if (r.prioInput.value === '' || !Number.isInteger(p) || p < -1000 || p > 1000) {
        setText($('jobs-note'), `job ${id}: a priority is a whole number from -1000 to 1000`);
        return;
      }
      jobAction(id, 'priority', {priority: p}, r.prioInput);
    });
    r.prio.append(r.prioForm);
    r.actions = el('td', 'actions');
    r.view = actionButton('Preview', 'small', () => selectJob(id));
    r.view.setAttribute('aria-label', `Preview job ${id}`);
    r.pause = actionButton('Pause', 'small writer-only', () => jobAction(id, 'pause'));
    r.resume = actionButton('Resume', 'small writer-only', () => jobAction(id, 'resume'));
    r.cancel = actionButton('Cancel', 'small danger writer-only', async () => {
      if (await confirmAction(`Cancel job ${id}? Workers stop receiving its tiles; its stored tiles are kept and "Requeue" continues it.`, 'Cancel job'))
        jobAction(id, 'cancel');
    });
    r.requeue = actionButton('Requeue', 'small writer-only', async () => {
      if (await confirmAction(`Requeue job ${id}? It is rendered again from the tiles it lacks.`, 'Requeue job'))
        jobAction(id, 'requeue');
    });
    for (const b of [r.pause, r.resume, r.cancel, r.requeue])
      b.setAttribute('aria-label', `${b.textContent} job ${id}`);
    const box = el('div', 'actions-box');
    box.append(r.view, r.pause, r.resume, r.cancel, r.requeue);
    r.actions.append(box);
    tr.append(r.id, r.output, r.state, r.progress, r.frames, r.elapsed, r.eta, r.spp, r.prio, r.actions);
    return r;
  }

  function updateJobRow(r, j) {
    r.job = j;
    setText(r.id, String(j.id));
    setText(r.output, j.output || '');
    setTitle(r.output, j.output || '');
    setText(r.stateBadge, j.state);
    r.stateBadge.className = `badge state-${j.state}`;
    const total = j.tiles_total || 0;
    const done = j.tiles_done || 0;
    const frac = total > 0 ? done / total : (j.state === 'done' ? 1 : 0);
    if (r.bar.value !== frac) r.bar.value = frac;
    r.bar.setAttribute('aria-label', `job ${j.id}: ${numFmt.format(done)} of ${numFmt.format(total)} tiles`);
    setText(r.tiles, `${numFmt.format(done)}/${numFmt.format(total)}`);
    if (j.frames_total !== undefined && j.frames_total > 1)
      setText(r.frames, `${numFmt.format(j.frames_done || 0)}/${numFmt.format(j.frames_total)}`);
    else
      setText(r.frames, '1');
    const finished = j.state === 'done' || j.state === 'cancelled';
    setText(r.elapsed, duration(j.elapsed_s));
    const noWorker = j.no_worker_s !== undefined && j.no_worker_s !== null;
    setText(r.eta, noWorker ? 'no worker' : finished ? '–' : duration(j.eta_s));
    setTitle(r.eta, noWorker ? `no worker for ${duration(j.no_worker_s)}` : '');
    // Adaptive jobs: the mean so far over the most; a uniform job's mean is its samples.
    const spp = j.mean_spp !== undefined && j.mean_spp !== null && j.mean_spp !== j.samples
      ? `${oneFmt.format(j.mean_spp)}/${numFmt.format(j.samples)}` : numFmt.format(j.samples);
    setText(r.spp, spp);
    if (document.activeElement !== r.prioInput && r.prioInput.value !== String(j.priority))
      r.prioInput.value = String(j.priority);
    r.prioInput.disabled = j.state === 'done' || readOnly();
    r.prioSet.disabled = j.state === 'done' || readOnly();
    r.pause.hidden = !(j.state === 'queued' || j.state === 'rendering');
    r.resume.hidden = j.state !== 'paused';
    r.cancel.hidden = finished;
    r.requeue.hidden = j.state !== 'cancelled';
    r.tr.classList.toggle('selected', preview.job === j.id);
    r.view.setAttribute('aria-pressed', preview.job === j.id ? 'true' : 'false');
  }

  async function pollJobs() {
    const g = await get(`/ui/api/jobs?limit=${JOBS_LIMIT}`, jobsEtag);
    if (g.status === 304) return POLL_MS;
    const body = await g.res.json();
    jobsEtag = g.etag;
    const jobs = (body.jobs || []).slice().reverse();   // newest first
    const tbody = $('jobs').tBodies[0];
    const seen = new Set();
    let prev = null;
    for (const j of jobs) {
      seen.add(j.id);
      let r = jobRows.get(j.id);
      if (!r) {
        r = makeJobRow(j.id);
        jobRows.set(j.id, r);
      }
      updateJobRow(r, j);
      const want = prev ? prev.nextSibling : tbody.firstChild;
      if (want !== r.tr) tbody.insertBefore(r.tr, want);
      prev = r.tr;
    }
    for (const [id, r] of jobRows) {
      if (!seen.has(id)) {
        r.tr.remove();
        jobRows.delete(id);
      }
    }
    $('jobs-empty').hidden = jobs.length > 0;
    setText($('jobs-note'), jobs.length >= JOBS_LIMIT ? `the newest ${JOBS_LIMIT}` : '');
    if (preview.job !== null) {
      const r = jobRows.get(preview.job);
      if (r) updatePreviewTitle(r.job);
    }
    return POLL_MS;
  }

  async function jobAction(id, verb, body, focusBack) {
    if (readOnly()) return;
    setText($('jobs-note'), '');
    try {
      await post(`/ui/api/jobs/${id}/${verb}`, body === undefined ? undefined : body);
      setText($('jobs-note'), `job ${id}: ${verb} done`);
    } catch (e) {
      if (e instanceof Unauthorized) return;
      setText($('jobs-note'), `job ${id}: ${verb} failed: ${e.message}`);
    }
    jobsEtag = null;
    jobsPoller.kick(0);
    if (preview.job === id) tilesPoller.kick(0);
    if (focusBack) focusBack.focus();
  }

  // ---- the confirmation dialog ----
  function confirmAction(text, yesLabel) {
    const dlg = $('confirm');
    setText($('confirm-text'), text);
    setText($('confirm-yes'), yesLabel);
    const back = document.activeElement;
    return new Promise((resolve) => {
      const done = (ok) => {
        $('confirm-yes').removeEventListener('click', yes);
        $('confirm-no').removeEventListener('click', no);
        dlg.removeEventListener('cancel', no);
        if (dlg.open) dlg.close();
        if (back && back.focus) back.focus();
        resolve(ok);
      };
      const yes = () => done(true);
      const no = (ev) => {
        if (ev) ev.preventDefault();
        done(false);
      };
      $('confirm-yes').addEventListener('click', yes);
      $('confirm-no').addEventListener('click', no);
      dlg.addEventListener('cancel', no);
      dlg.showModal();
      $('confirm-no').focus();
    });
  }

  // ---- workers ----
  const workerRows = new Map();   // name + '@' + peer -> row
  let workersEtag = null;

  function resetWorkers() {
    workersEtag = null;
    for (const r of workerRows.values()) r.tr.remove();
    workerRows.clear();
    $('workers-empty').hidden = false;
  }

  function makeWorkerRow() {
    const r = {tr: el('tr')};
    r.name = el('td', 'ellipsis');
    r.status = el('td');
    r.badge = el('span', 'badge');
    r.status.append(r.badge);
    r.isa = el('td', 'opt');
    r.threads = el('td', 'num opt');
    r.seen = el('td', 'num');
    r.tiles = el('td', 'num');
    r.rays = el('td', 'num');
    r.tr.append(r.name, r.status, r.isa, r.threads, r.seen, r.tiles, r.rays);
    return r;
  }

  async function pollWorkers() {
    const g = await get('/ui/api/workers', workersEtag);
    if (g.status === 304) return POLL_MS;
    const body = await g.res.json();
    workersEtag = g.etag;
    const now = Date.now();
    const windowS = body.recent_window_s || 0;
    const tbody = $('workers').tBodies[0];
    const seen = new Set();
    let prev = null;
    for (const w of body.workers || []) {
      const key = `${w.name}@${w.peer}`;
      seen.add(key);
      let r = workerRows.get(key);
      if (!r) {
        r = makeWorkerRow();
        workerRows.set(key, r);
      }
      r.tr.dataset.worker = w.name;
      setText(r.name, w.name);
      setTitle(r.name, `${w.name} at ${w.peer}; ${numFmt.format(w.tiles)} tiles stored, ` +
                       `${numFmt.format(w.leases)} leases, ${numFmt.format(w.duplicates)} duplicates`);
      const faulty = (w.faulty_duplicates || 0) > 0 || (w.refused || 0) > 0;
      let status = 'ok';
      if (faulty) status = 'faulty';
      else if (w.quiet) status = 'quiet';
      setText(r.badge, status === 'faulty' ? '⚠ faulty' : status === 'quiet' ? '◌ quiet' : '● active');
      r.badge.className = `badge worker-${status}`;
      setTitle(r.badge, faulty
        ? `${w.faulty_duplicates} duplicate tiles differed, ${w.refused} uploads refused`
        : w.quiet ? `not seen for ${duration(w.last_seen_s)}` : 'seen recently');
      r.tr.classList.toggle('row-quiet', status === 'quiet');
      r.tr.classList.toggle('row-faulty', status === 'faulty');
      setText(r.isa, w.isa || '–');
      setText(r.threads, w.threads ? numFmt.format(w.threads) : '–');
      setText(r.seen, ago(w.last_seen_s));
      setTitle(r.seen, dateFmt.format(new Date(now - w.last_seen_s * 1000)));
      setText(r.tiles, numFmt.format(w.recent_tiles || 0));
      const mrays = windowS > 0 ? (w.recent_rays || 0) / windowS / 1e6 : 0;
      setText(r.rays, twoFmt.format(mrays));
      const want = prev ? prev.nextSibling : tbody.firstChild;
      if (want !== r.tr) tbody.insertBefore(r.tr, want);
      prev = r.tr;
    }
    for (const [key, r] of workerRows) {
      if (!seen.has(key)) {
        r.tr.remove();
        workerRows.delete(key);
      }
    }
    $('workers-empty').hidden = workerRows.size > 0;
    setText($('workers-note'), windowS > 0 ? `recent: the last ${duration(windowS)}` : '');
    return POLL_MS;
  }

  // ---- the preview ----
  const canvas = $('preview');
  const overlay = $('overlay');
  const ctx = canvas.getContext('2d', {alpha: false});
  const octx = overlay.getContext('2d');
  const preview = {
    job: null, generation: null, shownFrame: null, seq: 0, etag: null, width: 0, height: 0,
    written: false, imageShown: false, stored: [], leased: [], drag: null, hover: null,
    loaded: false,
  };

  function updatePreviewTitle(j) {
    setText($('preview-job'), j ? `of job ${j.id}` : '');
  }

  function selectJob(id) {
    tilesPoller.stop();
    preview.job = id;
    preview.generation = null;
    preview.shownFrame = null;
    preview.width = 0;
    preview.height = 0;
    preview.seq = 0;
    preview.etag = null;
    preview.written = false;
    preview.imageShown = false;
    preview.stored = [];
    preview.leased = [];
    preview.drag = null;
    preview.loaded = false;
    canvas.dataset.ready = 'false';
    $('tip').hidden = true;
    $('preview-box').hidden = id === null;
    $('focus-form').hidden = id === null;
    $('preview-empty').hidden = id !== null;
    setText($('preview-info'), '');
    setText($('focus-result'), '');
    for (const r of jobRows.values()) {
      r.tr.classList.toggle('selected', r.job !== null && r.job.id === id);
      r.view.setAttribute('aria-pressed', r.job !== null && r.job.id === id ? 'true' : 'false');
    }
    const r = id !== null ? jobRows.get(id) : null;
    updatePreviewTitle(r ? r.job : null);
    if (id !== null && signedIn) tilesPoller.start();
  }

  function resizePreview(w, h) {
    if (canvas.width !== w || canvas.height !== h) {
      canvas.width = w;
      canvas.height = h;
      overlay.width = w;
      overlay.height = h;
    }
    ctx.fillStyle = '#000';
    ctx.fillRect(0, 0, w, h);
    $('focus-x').max = String(w - 1);
    $('focus-y').max = String(h - 1);
    $('focus-w').max = String(w);
    $('focus-h').max = String(h);
  }

  function base64Bytes(b64) {
    const bin = atob(b64);
    const out = new Uint8Array(bin.length);
    for (let i = 0; i < bin.length; ++i) out[i] = bin.charCodeAt(i);
    return out;
  }

  const bitmapOptions = {colorSpaceConversion: 'none', premultiplyAlpha: 'none'};

  async function pollTiles() {
    const id = preview.job;
    if (id === null) return POLL_MS;
    const path = `/ui/api/jobs/${id}/tiles?since=${preview.seq}`;
    let g;
    try {
      g = await get(path, preview.etag);
    } catch (e) {
      if (e instanceof HttpError && e.status === 404 && preview.job === id) {
        setText($('preview-info'), `job ${id} is gone`);
        tilesPoller.stop();
        return POLL_MS;
      }
      throw e;
    }
    if (preview.job !== id) return 0;
    if (g.status === 304) return POLL_MS;
    const d = await g.res.json();
    if (preview.job !== id) return 0;

    // A restarted collector, the next frame, or another size: start again from nothing.
    const restart = d.generation !== preview.generation || d.frame !== preview.shownFrame ||
      d.width !== preview.width || d.height !== preview.height;
    if (restart && preview.seq !== 0) {
      preview.seq = 0;
      preview.etag = null;
      return 0;
    }
    if (restart) {
      preview.generation = d.generation;
      preview.shownFrame = d.frame;
      preview.width = d.width;
      preview.height = d.height;
      preview.stored = [];
      preview.imageShown = false;
      resizePreview(d.width, d.height);
    }
    // A capped answer is continued at once, unconditionally (its ETag is not the whole state's).
    preview.etag = d.more ? null : g.etag;
    preview.leased = d.leased || [];
    preview.written = !!d.written;

    if (d.written) {
      if (!preview.imageShown) {
        const frameQuery = d.frames_total > 1 ? `?frame=${d.frame}` : '';
        const img = await get(`/ui/api/jobs/${id}/image${frameQuery}`, null);
        if (preview.job !== id) return 0;
        const bitmap = await createImageBitmap(await img.res.blob(), bitmapOptions);
        if (preview.job !== id) return 0;
        if (bitmap.width === canvas.width && bitmap.height === canvas.height) {
          ctx.drawImage(bitmap, 0, 0);
        }
        bitmap.close();
        preview.imageShown = true;
      }
    } else if (d.tiles && d.tiles.length > 0 && d.atlas) {
      const blob = new Blob([base64Bytes(d.atlas)], {type: 'image/png'});
      const bitmap = await createImageBitmap(blob, bitmapOptions);
      if (preview.job !== id) {
        bitmap.close();
        return 0;
      }
      for (const t of d.tiles) {
        ctx.drawImage(bitmap, t.ax, t.ay, t.width, t.height, t.x, t.y, t.width, t.height);
        preview.stored.push(t);
      }
      bitmap.close();
    }
    preview.seq = d.seq;
    preview.loaded = !d.more;
    drawOverlay();
    const frames = d.frames_total > 1 ? `, frame ${d.frame} (${d.frame_index + 1} of ${d.frames_total})` : '';
    setText($('preview-info'),
            `${d.width}×${d.height}${frames}, ${d.state}; ${numFmt.format(preview.leased.length)} tiles rendering`);
    canvas.dataset.seq = String(d.seq);
    canvas.dataset.state = d.state;
    canvas.dataset.written = String(!!d.written);
    canvas.dataset.frame = String(d.frame);
    canvas.dataset.ready = String(!d.more);
    return d.more ? 0 : POLL_MS;
  }

  function drawOverlay() {
    octx.clearRect(0, 0, overlay.width, overlay.height);
    const scale = overlay.width / Math.max(1, overlay.getBoundingClientRect().width || overlay.width);
    const lw = Math.max(1, Math.round(2 * scale));
    octx.lineWidth = lw;
    octx.strokeStyle = 'rgba(255, 196, 0, 0.95)';
    for (const t of preview.leased)
      octx.strokeRect(t.x + lw / 2, t.y + lw / 2, Math.max(1, t.width - lw), Math.max(1, t.height - lw));
    const d = preview.drag;
    if (d && d.moved) {
      const r = dragRect(d);
      octx.strokeStyle = 'rgba(80, 200, 255, 1)';
      octx.setLineDash([4 * scale, 3 * scale]);
      octx.strokeRect(r.x + 0.5, r.y + 0.5, r.width, r.height);
      octx.setLineDash([]);
    }
  }

  // Where an event is, in image pixels (the canvas is scaled by CSS).
  function imagePoint(ev) {
    const b = overlay.getBoundingClientRect();
    const x = Math.floor((ev.clientX - b.left) * overlay.width / b.width);
    const y = Math.floor((ev.clientY - b.top) * overlay.height / b.height);
    return {x: Math.min(Math.max(x, 0), overlay.width - 1), y: Math.min(Math.max(y, 0), overlay.height - 1)};
  }

  function dragRect(d) {
    const x0 = Math.min(d.x0, d.x1), y0 = Math.min(d.y0, d.y1);
    return {x: x0, y: y0, width: Math.abs(d.x1 - d.x0) + 1, height: Math.abs(d.y1 - d.y0) + 1};
  }

  function tileAt(p) {
    const inside = (t) => p.x >= t.x && p.x < t.x + t.width && p.y >= t.y && p.y < t.y + t.height;
    for (const t of preview.leased) if (inside(t)) return {t, leased: true};
    for (let i = preview.stored.length - 1; i >= 0; --i)
      if (inside(preview.stored[i])) return {t: preview.stored[i], leased: false};
    return null;
  }

  function showTip(ev) {
    const tip = $('tip');
    const hit = tileAt(imagePoint(ev));
    if (!hit) {
      tip.hidden = true;
      return;
    }
    const who = hit.t.worker || 'an unknown worker';
    setText(tip, `tile ${hit.t.tile}: ${hit.leased ? 'rendering on' : 'rendered by'} ${who}`);
    const box = $('preview-box').getBoundingClientRect();
    tip.style.left = `${Math.min(ev.clientX - box.left + 12, Math.max(0, box.width - 220))}px`;
    tip.style.top = `${ev.clientY - box.top + 14}px`;
    tip.hidden = false;
  }

  overlay.addEventListener('pointerdown', (ev) => {
    if (ev.button !== 0 || preview.job === null || readOnly()) return;
    const p = imagePoint(ev);
    preview.drag = {x0: p.x, y0: p.y, x1: p.x, y1: p.y, cx: ev.clientX, cy: ev.clientY, moved: false};
    overlay.setPointerCapture(ev.pointerId);
    ev.preventDefault();
  });
  overlay.addEventListener('pointermove', (ev) => {
    const d = preview.drag;
    if (d) {
      const p = imagePoint(ev);
      d.x1 = p.x;
      d.y1 = p.y;
      if (Math.abs(ev.clientX - d.cx) + Math.abs(ev.clientY - d.cy) > 4) d.moved = true;
      drawOverlay();
    } else {
      showTip(ev);
    }
  });
  overlay.addEventListener('pointerleave', () => {
    $('tip').hidden = true;
  });
  overlay.addEventListener('pointercancel', () => {
    preview.drag = null;
    drawOverlay();
  });
  overlay.addEventListener('pointerup', (ev) => {
    const d = preview.drag;
    if (!d) return;
    preview.drag = null;
    const r = d.moved ? dragRect(d) : {x: d.x0, y: d.y0, width: 1, height: 1};
    drawOverlay();
    $('focus-x').value = String(r.x);
    $('focus-y').value = String(r.y);
    $('focus-w').value = String(r.width);
    $('focus-h').value = String(r.height);
    focusRegion(r);
  });

  $('focus-form').addEventListener('submit', (ev) => {
    ev.preventDefault();
    const r = {
      x: Number($('focus-x').value), y: Number($('focus-y').value),
      width: Number($('focus-w').value), height: Number($('focus-h').value),
    };
    focusRegion(r);
  });

  async function focusRegion(r) {
    const id = preview.job;
    if (id === null || readOnly()) return;
    setText($('focus-result'), '');
    try {
      const body = await post(`/ui/api/jobs/${id}/focus`, r);
      const n = body && typeof body.tiles === 'number' ? body.tiles : 0;
      setText($('focus-result'),
              n > 0 ? `${numFmt.format(n)} tiles of ${r.width}×${r.height} at (${r.x}, ${r.y}) moved to the front`
                    : `no unfinished tile in ${r.width}×${r.height} at (${r.x}, ${r.y})`);
    } catch (e) {
      if (e instanceof Unauthorized) return;
      setText($('focus-result'), `not moved: ${e.message}`);
    }
    tilesPoller.kick(0);
  }

  window.addEventListener('resize', () => drawOverlay());

  // ---- start: signed in already? ----
  async function boot() {
    try {
      const res = await fetch('/ui/session', {credentials: 'same-origin', cache: 'no-store'});
      const answer = res.ok ? await res.json() : null;
      if (answer && answer.signed_in) {
        csrf = answer.csrf;
        showSignedIn(answer.role);
        return;
      }
      showSignedOut(res.ok ? '' : 'The collector refused the page.');
    } catch (e) {
      showSignedOut('The collector does not answer.');
    }
  }
  boot();
})();
