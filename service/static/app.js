/* sarship web page: jobs (live), scene upload (with its ingest job followed), submit form built
 * from the process schemas (main parameters open, the others in a collapsed "Advanced
 * parameters"), job view with the quicklook tiles on a Leaflet map (a georeferenced scene: in
 * lon/lat on a Web Mercator map with a graticule, tiles warped into place; else CRS.Simple over
 * the scene's pixel grid), the detections drawn and listed and the scores when the scene has
 * ground truth, scheduled-ingest state.
 *
 * Everything comes from the public API (relative to this page: the API root is "../"), so the
 * page works behind a path prefix. Text from the API is only ever put into the page as text
 * nodes (textContent / append(string)); links from the API are restricted to http(s).
 *
 * One file of about 1200 lines, on purpose: the page is served as static files with no build
 * step and no bundler, and its views share one small state and fetch helpers inside one
 * closure; split into ES modules it would gain imports, not clarity.
 */
'use strict';

(() => {
  const API = new URL('../', window.location.href);
  const TOKEN_KEY = 'sarship.token';
  const ACTIVE = new Set(['accepted', 'running']);
  const FAST_MS = 1000;     // job list poll while some job is active
  const IDLE_MS = 10000;    // ... while none is (jobs may still arrive from others or the ingest loop)
  const INGEST_MS = 5000;
  const MAX_ROWS = 2000;    // detections listed in the table (all are drawn)

  const $ = (id) => document.getElementById(id);
  const api = (path) => new URL(path, API).toString();

  // ---------------------------------------------------------------- DOM and HTTP helpers

  /** Only http(s) links from the API become hrefs (no javascript:, data: ...). */
  function safeHref(u) {
    try {
      const x = new URL(u, window.location.href);
      return (x.protocol === 'http:' || x.protocol === 'https:') ? x.href : '#';
    } catch (e) {
      return '#';
    }
  }

  /** createElement with attributes, listeners (onclick...) and children; strings become text nodes. */
  function h(tag, attrs, ...kids) {
    const el = document.createElement(tag);
    for (const [k, v] of Object.entries(attrs || {})) {
      if (v === null || v === undefined || v === false) continue;
      if (k === 'class') el.className = v;
      else if (k === 'dataset') Object.assign(el.dataset, v);
      else if (k.startsWith('on')) el.addEventListener(k.slice(2), v);
      else if (k === 'href') el.setAttribute('href', safeHref(v));
      else el.setAttribute(k, v === true ? '' : String(v));
    }
    for (const c of kids.flat()) {
      if (c !== null && c !== undefined && c !== false) el.append(c instanceof Node ? c : String(c));
    }
    return el;
  }

  function token() {
    try { return window.localStorage.getItem(TOKEN_KEY) || ''; } catch (e) { return ''; }
  }

  function authHeaders() {
    const t = token();
    return t ? { Authorization: 'Bearer ' + t } : {};
  }

  class ApiError extends Error {
    constructor(status, title, detail) {
      super(`${status} ${title}: ${detail}`);
      this.status = status;
      this.title = title;
      this.detail = detail;
    }
  }

  /** fetch JSON from the API with the token; a non-2xx answer throws ApiError(title, detail). */
  async function getJSON(url, opts = {}) {
    const r = await fetch(url, {
      ...opts,
      headers: { Accept: 'application/json', ...authHeaders(), ...(opts.headers || {}) },
    });
    const ct = r.headers.get('content-type') || '';
    const body = ct.includes('json') ? await r.json().catch(() => null) : await r.text().catch(() => '');
    if (!r.ok) {
      const p = (body && typeof body === 'object') ? body : {};
      throw new ApiError(r.status, p.title || r.statusText || 'error', p.detail || (typeof body === 'string' && body) || `HTTP ${r.status}`);
    }
    return body;
  }

  /** Show an error (ApiError or other) in a role=alert box; null hides it. */
  function showProblem(box, err) {
    box.replaceChildren();
    if (!err) { box.hidden = true; return; }
    if (err instanceof ApiError) {
      box.append(h('strong', {}, `${err.status} ${err.title}`.trim()), ': ', h('span', { class: 'detail' }, err.detail));
    } else {
      box.append(h('strong', {}, 'error'), ': ', h('span', { class: 'detail' }, String(err && err.message || err)));
    }
    box.hidden = false;
  }

  const pad2 = (n) => String(n).padStart(2, '0');
  function fmtTime(iso) {
    if (!iso) return '';
    const d = new Date(iso);
    if (Number.isNaN(d.getTime())) return String(iso);
    return `${d.getFullYear()}-${pad2(d.getMonth() + 1)}-${pad2(d.getDate())} ` +
      `${pad2(d.getHours())}:${pad2(d.getMinutes())}:${pad2(d.getSeconds())}`;
  }
  function fmtNum(x, digits = 4) {
    if (x === null || x === undefined || x === '') return '';
    if (typeof x !== 'number') return String(x);
    if (Number.isInteger(x)) return String(x);
    return Number(x.toPrecision(digits)).toString();
  }

  function statusBadge(status) {
    return h('span', { class: `status status-${String(status).replace(/[^a-z]/g, '')}` }, status);
  }

  function progressBar(p, label) {
    const v = Math.max(0, Math.min(100, Number(p) || 0));
    return h('span', { class: 'prog' }, h('progress', { max: 100, value: v, 'aria-label': label }), ` ${v}%`);
  }

  // ---------------------------------------------------------------- token

  function initToken() {
    const input = $('token');
    const state = $('token-state');
    const show = () => { state.textContent = token() ? 'A token is set: requests carry it.' : 'No token set.'; };
    input.value = token();
    show();
    $('token-form').addEventListener('submit', (ev) => {
      ev.preventDefault();
      try { window.localStorage.setItem(TOKEN_KEY, input.value.trim()); } catch (e) { /* private mode */ }
      show();
      refreshAll();
    });
    $('token-clear').addEventListener('click', () => {
      try { window.localStorage.removeItem(TOKEN_KEY); } catch (e) { /* private mode */ }
      input.value = '';
      show();
    });
  }

  // ---------------------------------------------------------------- dashboard link

  /** Probe GET /dashboard without following its (cross-origin) redirect: a redirect keeps the
   *  link; anything else (404 when the scheduler serves no dashboard) disables it, its title
   *  saying how to enable it. */
  async function checkDashboard() {
    const a = $('dashboard-link');
    let why = 'the Dask dashboard cannot be reached';
    try {
      const r = await fetch(api('dashboard'), { redirect: 'manual', headers: authHeaders() });
      if (r.type === 'opaqueredirect' || r.ok) return;
      why = (await r.json()).detail || why;
    } catch (e) { /* no answer, or not JSON: the default reason */ }
    a.removeAttribute('href');
    a.setAttribute('aria-disabled', 'true');
    a.title = why;
    a.append(' (not available)');
  }

  // ---------------------------------------------------------------- submit form

  const processCache = new Map();

  async function loadScenes() {
    const sel = $('scene-select');
    let scenes = [];
    try {
      scenes = (await getJSON(api('scenes'))).scenes || [];
    } catch (e) {
      showProblem($('submit-error'), e);
    }
    // the choice as it is now, after the wait: a refresh started before an upload chose its new
    // scene must not put the older choice back
    const keep = sel.value;
    const opts = scenes.map((s) => {
      const ready = s.status === 'ready';
      const info = ready ? [Array.isArray(s.shape) ? s.shape.join('×') : '', s.kind,
        s.acquired ? String(s.acquired).replace('T', ' ').slice(0, 16) : ''].filter(Boolean).join(', ')
        : s.status;
      // the product (or uploaded file) name first: a hash alone says nothing to a person
      const name = s.product || s.filename;
      const label = name && name !== s.sceneID ? `${name} · ${s.sceneID}` : s.sceneID;
      return h('option', { value: s.sceneID, disabled: !ready, title: s.filename || s.sceneID },
        info ? `${label} (${info})` : label);
    });
    if (!opts.length) opts.push(h('option', { value: '' }, '(no scenes: give a path)'));
    sel.replaceChildren(...opts);
    if (keep && scenes.some((s) => s.sceneID === keep)) sel.value = keep;
  }

  async function loadProcesses() {
    const sel = $('process');
    const doc = await getJSON(api('processes'));
    const procs = doc.processes || [];
    sel.replaceChildren(...procs.map((p) => h('option', { value: p.id }, p.title && p.title !== p.id ? `${p.id}: ${p.title}` : p.id)));
    const pre = procs.find((p) => p.id === 'ca_cfar') || procs[0];
    if (pre) sel.value = pre.id;
    await renderParams();
  }

  async function describe(id) {
    if (!processCache.has(id)) processCache.set(id, await getJSON(api(`processes/${encodeURIComponent(id)}`)));
    return processCache.get(id);
  }

  /** The schema of one input, with anyOf [X, null] and $ref resolved: {s, nullable}. */
  function resolveSchema(schema) {
    const defs = schema.$defs || {};
    const deref = (x) => {
      let y = x;
      for (let i = 0; i < 8 && y && y.$ref; i++) y = { ...defs[String(y.$ref).split('/').pop()], ...y, $ref: undefined };
      if (y && Array.isArray(y.allOf) && y.allOf.length === 1) y = { ...deref(y.allOf[0]), ...y, allOf: undefined };
      return y || {};
    };
    let s = deref(schema);
    let nullable = false;
    const alts = s.anyOf || s.oneOf;
    if (Array.isArray(alts)) {
      const real = alts.map(deref).filter((a) => a.type !== 'null');
      nullable = real.length < alts.length;
      if (real.length === 1) s = { ...real[0], default: s.default, title: s.title, description: s.description };
      else s = { ...s, type: 'string' };
    }
    if (Array.isArray(s.type)) {
      nullable = nullable || s.type.includes('null');
      s = { ...s, type: s.type.find((t) => t !== 'null') || 'string' };
    }
    if (!s.enum && typeof s.pattern === 'string') {  // pydantic "^(a|b|c)$" patterns: a choice
      const m = s.pattern.match(/^\^\(([A-Za-z0-9_.|-]+)\)\$$/);
      if (m) s = { ...s, enum: m[1].split('|') };
    }
    return { s, nullable };
  }

  function rangeText(s) {
    const parts = [];
    if (s.minimum !== undefined) parts.push(`≥ ${s.minimum}`);
    if (s.exclusiveMinimum !== undefined) parts.push(`> ${s.exclusiveMinimum}`);
    if (s.maximum !== undefined) parts.push(`≤ ${s.maximum}`);
    if (s.exclusiveMaximum !== undefined) parts.push(`< ${s.exclusiveMaximum}`);
    return parts.join(', ');
  }

  /** One labelled form control for a process input. */
  function paramField(name, input) {
    const { s, nullable } = resolveSchema(input.schema || {});
    const id = `param-${name}`;
    const helpId = `${id}-help`;
    const def = s.default;
    let kind;
    let ctl;
    if (Array.isArray(s.enum)) {
      kind = 'enum';
      const opts = s.enum.map((v) => h('option', { value: String(v) }, String(v)));
      if (nullable || def === undefined) opts.unshift(h('option', { value: '' }, '(default)'));
      ctl = h('select', { id, name }, opts);
      ctl.value = def === undefined || def === null ? '' : String(def);
    } else if (s.type === 'boolean') {
      kind = 'bool';
      ctl = h('input', { id, name, type: 'checkbox' });
      ctl.checked = def === true;
    } else if (s.type === 'integer' || s.type === 'number') {
      kind = s.type === 'integer' ? 'int' : 'num';
      ctl = h('input', {
        id, name, type: 'number', inputmode: kind === 'int' ? 'numeric' : 'decimal',
        step: kind === 'int' ? 1 : 'any', min: s.minimum, max: s.maximum,
        placeholder: nullable ? 'automatic' : null,
      });
      ctl.value = def === undefined || def === null ? '' : String(def);
    } else {
      kind = 'str';
      ctl = h('input', { id, name, type: 'text', spellcheck: 'false', placeholder: nullable ? 'automatic' : null });
      ctl.value = def === undefined || def === null ? '' : String(def);
    }
    ctl.dataset.param = name;
    ctl.dataset.kind = kind;
    ctl.dataset.default = JSON.stringify(def === undefined ? null : def);
    ctl.setAttribute('aria-describedby', helpId);
    const req = (input.minOccurs || 0) > 0;
    if (req) ctl.required = true;
    const hint = [input.description || s.description || '', rangeText(s) && `(${rangeText(s)})`,
      nullable ? 'Empty: chosen automatically.' : ''].filter(Boolean).join(' ');
    const label = h('label', { for: id }, input.title && input.title.toLowerCase() !== name.replace(/_/g, ' ')
      ? `${name} (${input.title})` : name);
    return h('div', { class: kind === 'bool' ? 'field check' : 'field' }, label, ctl, h('p', { id: helpId, class: 'hint' }, hint));
  }

  async function renderParams() {
    const fs = $('params');
    const id = $('process').value;
    if (!id) return;
    let desc;
    try {
      desc = await describe(id);
    } catch (e) {
      showProblem($('submit-error'), e);
      return;
    }
    $('process-help').textContent = [desc.description, desc.reference && `(${desc.reference})`].filter(Boolean).join(' ');
    const inputs = Object.entries(desc.inputs || {}).filter(([k]) => k !== 'scene');
    // device first (where the job runs), then the detector's own parameters in schema order
    inputs.sort((a, b) => (b[0] === 'device') - (a[0] === 'device'));
    const main = inputs.filter(([k, v]) => isMain(k, v));
    const rest = inputs.filter(([k, v]) => !isMain(k, v));
    const adv = rest.length ? h('details', { id: 'advanced', class: 'advanced' },
      h('summary', {}, `Advanced parameters (${rest.length})`),
      h('p', { class: 'hint' }, 'Their defaults suit most scenes; a changed value is sent, the others are left to the detector.'),
      ...rest.map(([k, v]) => paramField(k, v))) : null;
    fs.replaceChildren(h('legend', {}, `Parameters of ${id}`), ...main.map(([k, v]) => paramField(k, v)), adv);
  }

  /** The parameters shown open: where the job runs, the false-alarm rate (the operating point) and
   * the CFAR windows (set from the ships' size in pixels), plus any required input; the other
   * inputs of a detector (size filters, land mask, sidelobes, ambiguities, fit details ...) are
   * in the collapsed "Advanced parameters". */
  const MAIN_PARAMS = new Set(['device', 'pfa', 'guard', 'background']);
  const isMain = (name, input) => MAIN_PARAMS.has(name) || (input.minOccurs || 0) > 0;

  /** The inputs document: the scene and every parameter that differs from its default. */
  function collectInputs() {
    const scene = $('scene-path').value.trim() || $('scene-select').value;
    const inputs = { scene };
    for (const el of $('params').querySelectorAll('[data-param]')) {
      const name = el.dataset.param;
      const def = JSON.parse(el.dataset.default);
      let v;
      if (el.dataset.kind === 'bool') v = el.checked;
      else if (el.value === '') continue;
      else if (el.dataset.kind === 'int' || el.dataset.kind === 'num') v = Number(el.value);
      else v = el.value;
      if (v === def) continue;
      inputs[name] = v;
    }
    return inputs;
  }

  function markInvalid(detail) {
    for (const el of $('params').querySelectorAll('[data-param]')) {
      const re = new RegExp(`(^|[^A-Za-z0-9_])${el.dataset.param}([^A-Za-z0-9_]|$)`);
      if (detail && re.test(detail)) {
        el.setAttribute('aria-invalid', 'true');
        const adv = el.closest('details');
        if (adv) adv.open = true;  // the API named an advanced parameter: show it
      } else el.removeAttribute('aria-invalid');
    }
    const sceneBad = !!detail && /scene/.test(detail);
    for (const id of ['scene-select', 'scene-path']) {
      if (sceneBad) $(id).setAttribute('aria-invalid', 'true'); else $(id).removeAttribute('aria-invalid');
    }
  }

  async function submitJob(ev) {
    ev.preventDefault();
    const err = $('submit-error');
    const ok = $('submit-ok');
    const btn = $('submit-btn');
    const pid = $('process').value;
    showProblem(err, null);
    markInvalid(null);
    ok.replaceChildren();
    const inputs = collectInputs();
    if (!inputs.scene) {
      showProblem(err, new ApiError(400, 'missing input', 'choose a scene or give a scene path'));
      markInvalid('scene');
      return;
    }
    btn.disabled = true;
    try {
      const st = await getJSON(api(`processes/${encodeURIComponent(pid)}/execution`), {
        method: 'POST',
        headers: { 'Content-Type': 'application/json', Prefer: 'respond-async' },
        body: JSON.stringify({ inputs }),
      });
      ok.append('Job ', h('a', { href: `#/jobs/${encodeURIComponent(st.jobID)}` }, st.jobID), ` accepted (${pid}).`);
      pollSoon();
    } catch (e) {
      showProblem(err, e);
      if (e instanceof ApiError) markInvalid(e.detail);
    } finally {
      btn.disabled = false;
    }
  }

  function initForm() {
    $('process').addEventListener('change', () => { showProblem($('submit-error'), null); markInvalid(null); renderParams(); });
    $('reset-params').addEventListener('click', () => renderParams());
    $('submit-form').addEventListener('submit', submitJob);
  }

  // ---------------------------------------------------------------- scene upload

  /** POST a file to /scenes (raw body, ?filename=) with upload progress; resolves to the JSON
   * answer, rejects with ApiError (the problem document) or Error (network). */
  function postScene(file, onProgress) {
    return new Promise((resolve, reject) => {
      const xhr = new XMLHttpRequest();
      xhr.open('POST', api(`scenes?filename=${encodeURIComponent(file.name)}`));
      xhr.setRequestHeader('Accept', 'application/json');
      xhr.setRequestHeader('Content-Type', 'application/octet-stream');
      for (const [k, v] of Object.entries(authHeaders())) xhr.setRequestHeader(k, v);
      xhr.upload.addEventListener('progress', (ev) => { if (ev.lengthComputable) onProgress(ev.loaded / ev.total); });
      xhr.addEventListener('load', () => {
        let body = null;
        try { body = JSON.parse(xhr.responseText); } catch (e) { body = null; }
        if (xhr.status >= 200 && xhr.status < 300 && body) { resolve(body); return; }
        const p = (body && typeof body === 'object') ? body : {};
        reject(new ApiError(xhr.status, p.title || xhr.statusText || 'error', p.detail || xhr.responseText || `HTTP ${xhr.status}`));
      });
      xhr.addEventListener('error', () => reject(new Error('the upload failed (network error)')));
      xhr.addEventListener('abort', () => reject(new Error('the upload was aborted')));
      xhr.send(file);
    });
  }

  const sleep = (ms) => new Promise((r) => { setTimeout(r, ms); });

  function initUpload() {
    const form = $('upload-form');
    const input = $('upload-file');
    const btn = $('upload-btn');
    const err = $('upload-error');
    const state = $('upload-state');
    const bar = $('upload-bar');
    const pct = $('upload-pct');
    const setPct = (f) => { const v = Math.round(100 * f); bar.value = v; pct.textContent = `${v}%`; };
    const say = (...parts) => state.replaceChildren(...parts);
    form.addEventListener('submit', async (ev) => {
      ev.preventDefault();
      showProblem(err, null);
      input.removeAttribute('aria-invalid');
      const file = input.files && input.files[0];
      if (!file) {
        input.setAttribute('aria-invalid', 'true');
        showProblem(err, new Error('choose a file first'));
        return;
      }
      btn.disabled = true;
      $('upload-progress').hidden = false;
      setPct(0);
      say(`uploading ${file.name}…`);
      try {
        const doc = await postScene(file, setPct);
        setPct(1);
        const sid = doc.sceneID;
        const sceneEl = h('code', { id: 'upload-scene' }, sid);
        if (doc.status !== 'ready' && doc.jobID) {
          const jobA = h('a', { href: `#/jobs/${encodeURIComponent(doc.jobID)}`, class: 'job-chip', title: doc.jobID }, doc.jobID.slice(0, 8));
          say('scene ', sceneEl, ': ingesting (job ', jobA, ')…');
          pollSoon();
          for (;;) {  // the ingest job: until it is final
            await sleep(FAST_MS);
            const j = await getJSON(api(`jobs/${encodeURIComponent(doc.jobID)}`));
            if (j.status === 'successful') break;
            if (!ACTIVE.has(j.status)) throw new ApiError('', `ingest ${j.status}`, j.message || j.status);
            say('scene ', sceneEl, `: ingesting (job `, jobA, `, ${j.status} ${Number(j.progress) || 0}%)…`);
          }
        }
        await loadScenes();
        const sel = $('scene-select');
        if ([...sel.options].some((o) => o.value === sid && !o.disabled)) {
          sel.value = sid;
          $('scene-path').value = '';
        }
        say('scene ', sceneEl, ' is ready: selected in the form below.');
        state.dataset.scene = sid;
        input.value = '';
      } catch (e) {
        say('');
        showProblem(err, e);
        loadScenes();
      } finally {
        btn.disabled = false;
        pollSoon();
      }
    });
  }

  // ---------------------------------------------------------------- jobs list

  const rows = new Map();  // jobID -> <tr>
  let jobsTimer = null;
  let ingestedSeen = null;  // the successful ingest jobs seen by the last poll

  function jobRow(j) {
    const link = h('a', { href: `#/jobs/${encodeURIComponent(j.jobID)}`, class: 'job-link', title: j.jobID },
      j.jobID.slice(0, 8));
    const tr = h('tr', { dataset: { jobId: j.jobID } },
      h('td', {}, link), h('td', { class: 'c-proc' }), h('td', { class: 'c-status' }), h('td', { class: 'c-prog' }),
      h('td', { class: 'c-created' }), h('td', { class: 'c-msg' }), h('td', { class: 'c-act' }));
    tr.addEventListener('click', (ev) => {
      if (ev.target.closest('a, button')) return;
      window.location.hash = `#/jobs/${encodeURIComponent(j.jobID)}`;
    });
    return tr;
  }

  function updateRow(tr, j) {
    const key = [j.status, j.progress, j.message, j.processID].join('\u0000');
    if (tr.dataset.key === key) return;
    tr.dataset.key = key;
    tr.dataset.status = j.status;
    tr.querySelector('.c-proc').textContent = j.processID;
    tr.querySelector('.c-status').replaceChildren(statusBadge(j.status));
    tr.querySelector('.c-prog').replaceChildren(progressBar(j.progress, `progress of job ${j.jobID}`));
    tr.querySelector('.c-created').textContent = fmtTime(j.created);
    const msg = tr.querySelector('.c-msg');
    msg.textContent = j.message || '';
    msg.title = j.message || '';
    const act = tr.querySelector('.c-act');
    act.replaceChildren();
    if (ACTIVE.has(j.status)) {
      act.append(h('button', { type: 'button', class: 'small', 'aria-label': `Dismiss job ${j.jobID}`, onclick: () => dismiss(j.jobID) }, 'Dismiss'));
    }
  }

  function renderJobs(jobs) {
    const tbody = $('jobs-table').querySelector('tbody');
    const seen = new Set();
    jobs.forEach((j, i) => {
      seen.add(j.jobID);
      let tr = rows.get(j.jobID);
      if (!tr) { tr = jobRow(j); rows.set(j.jobID, tr); }
      updateRow(tr, j);
      if (tbody.children[i] !== tr) tbody.insertBefore(tr, tbody.children[i] || null);
      if (current.id === j.jobID) tr.setAttribute('aria-current', 'true'); else tr.removeAttribute('aria-current');
    });
    for (const [id, tr] of rows) if (!seen.has(id)) { tr.remove(); rows.delete(id); }
    $('jobs-empty').hidden = jobs.length > 0;
  }

  async function pollJobs() {
    clearTimeout(jobsTimer);
    let active = false;
    try {
      const doc = await getJSON(api('jobs?limit=100'));
      const jobs = (doc.jobs || []).slice().sort((a, b) => String(b.created).localeCompare(String(a.created)));
      showProblem($('jobs-error'), null);
      // an ingest job (upload or inbox) finished since the last poll: a new scene for the form
      const ingested = jobs.filter((j) => j.processID === 'ingest' && j.status === 'successful').map((j) => j.jobID).join(',');
      if (ingestedSeen !== null && ingested !== ingestedSeen) loadScenes();
      ingestedSeen = ingested;
      renderJobs(jobs);
      active = jobs.some((j) => ACTIVE.has(j.status));
      const mine = jobs.find((j) => j.jobID === current.id);
      if (mine) updateJobView(mine);
      else if (current.id && (ACTIVE.has(current.status) || !current.status)) await refreshJob();
    } catch (e) {
      showProblem($('jobs-error'), e);
    }
    $('jobs-live').textContent = active ? '(live)' : '';
    if (!document.hidden) jobsTimer = setTimeout(pollJobs, active ? FAST_MS : IDLE_MS);
  }

  function pollSoon() {
    clearTimeout(jobsTimer);
    jobsTimer = setTimeout(pollJobs, 150);
  }

  async function dismiss(id) {
    try {
      await getJSON(api(`jobs/${encodeURIComponent(id)}`), { method: 'DELETE' });
    } catch (e) {
      showProblem($('jobs-error'), e);
    }
    pollSoon();
  }

  // ---------------------------------------------------------------- job view

  /** The job on view: its id, last status, and the map/detections once it succeeded. */
  let current = { id: null };

  function route(ev) {
    const hash = window.location.hash;
    if (hash && !hash.startsWith('#/')) return;  // an in-page anchor (the skip link), not a view
    const m = hash.match(/^#\/jobs\/([^/?#]+)$/);
    let id = null;
    try { id = m ? decodeURIComponent(m[1]) : null; } catch (e) { id = m[1]; }  // malformed %-escape: as typed
    if (id === current.id) return;
    closeJob();
    if (!id) return;
    current = { id, status: null };
    const sec = $('job');
    sec.hidden = false;
    $('job-h').textContent = `Job ${id}`;
    $('job-body').replaceChildren(h('p', { class: 'hint' }, 'Loading…'));
    for (const [jid, tr] of rows) if (jid === id) tr.setAttribute('aria-current', 'true'); else tr.removeAttribute('aria-current');
    refreshJob();
    if (ev) $('job-h').focus();  // navigated here: move focus to the job (not on the first load)
  }

  function closeJob() {
    if (current.map) current.map.remove();
    current = { id: null };
    $('job').hidden = true;
    $('job-body').replaceChildren();
    for (const tr of rows.values()) tr.removeAttribute('aria-current');
  }

  async function refreshJob() {
    const id = current.id;
    try {
      const j = await getJSON(api(`jobs/${encodeURIComponent(id)}`));
      if (current.id === id) updateJobView(j);
    } catch (e) {
      if (current.id !== id) return;
      current.status = 'error';
      const box = h('div', { class: 'problem', role: 'alert' });
      showProblem(box, e);
      $('job-body').replaceChildren(box, h('p', {}, h('a', { href: '#/' }, 'Close')));
    }
  }

  function buildJobSkeleton() {
    const body = $('job-body');
    body.replaceChildren(
      h('div', { class: 'job-head' },
        h('dl', { class: 'kv', id: 'job-kv' }),
        h('div', { class: 'job-actions' },
          h('button', { type: 'button', id: 'job-dismiss', hidden: true, onclick: () => dismiss(current.id) }, 'Dismiss'),
          h('a', { href: '#/', class: 'button-like' }, 'Close'))),
      h('div', { id: 'job-status', role: 'status', 'aria-live': 'polite', class: 'job-status' }),
      h('div', { id: 'job-result' }));
    current.skeleton = true;
  }

  function kv(dl, pairs) {
    dl.replaceChildren(...pairs.filter(([, v]) => v !== null && v !== undefined && v !== '')
      .flatMap(([k, v]) => [h('dt', {}, k), h('dd', {}, v)]));
  }

  function updateJobView(j) {
    if (!current.skeleton) buildJobSkeleton();
    const key = [j.status, j.progress, j.message, j.finished].join('\u0000');
    if (current.key === key) return;
    current.key = key;
    const prev = current.status;
    current.status = j.status;
    kv($('job-kv'), [
      ['Detector', j.processID], ['Status', statusBadge(j.status)],
      ['Progress', progressBar(j.progress, 'job progress')], ['Created', fmtTime(j.created)],
      ['Started', fmtTime(j.started)], ['Finished', fmtTime(j.finished)], ['Attempts', j.attempts],
    ]);
    $('job-dismiss').hidden = !ACTIVE.has(j.status);
    $('job-status').textContent = j.message ? `${j.status}: ${j.message}` : j.status;
    if (j.status === 'successful' && j.processID === 'ingest') {
      $('job-result').replaceChildren(h('p', { class: 'hint' },
        'An ingest job makes a scene (listed in the form once ready); it has no detections.'));
    } else if (j.status === 'successful' && prev !== 'successful') loadResults(j);
    else if (j.status === 'failed') {
      const box = h('div', { class: 'problem' });
      showProblem(box, new ApiError('', 'job failed', j.message || 'no message'));
      $('job-result').replaceChildren(box);
    } else if (j.status === 'dismissed') {
      $('job-result').replaceChildren(h('p', { class: 'hint' }, 'This job was dismissed: it has no results.'));
    }
  }

  /** Z: the zoom at which one map pixel is one scene pixel (the tiles' maxzoom). */
  const nativeZoom = (H, W) => Math.max(0, Math.ceil(Math.log2(Math.max(H, W) / 256)));

  async function loadResults(j) {
    const id = j.jobID;
    const box = $('job-result');
    box.replaceChildren(h('p', { class: 'hint' }, 'Loading results…'));
    const jobUrl = (p) => api(`jobs/${encodeURIComponent(id)}/${p}`);
    let links;
    let fc;
    try {
      links = await getJSON(jobUrl('results'));
      fc = links.detections ? await getJSON(links.detections.href) : { features: [] };
    } catch (e) {
      const p = h('div', { class: 'problem', role: 'alert' });
      showProblem(p, e);
      box.replaceChildren(p);
      return;
    }
    if (current.id !== id) return;
    const feats = (fc.features || []).filter((f) => f && f.properties && Array.isArray(f.properties.bbox_px));
    const linkList = h('ul', { class: 'links' },
      Object.entries(links).filter(([, v]) => v && typeof v === 'object' && v.href).map(([k, v]) =>
        h('li', {}, h('a', { href: v.href, type: v.type, target: '_blank', rel: 'noopener' }, k),
          v.type ? h('span', { class: 'hint' }, ` ${v.type}`) : null)),
      h('li', {}, h('a', { href: jobUrl('preview.png'), type: 'image/png', target: '_blank', rel: 'noopener' }, 'preview'),
        h('span', { class: 'hint' }, ' image/png')));
    const mapEl = h('div', { id: 'map', class: 'map', role: 'region', 'aria-label': 'Scene quicklook with detections (arrow keys pan, + and - zoom)' });
    const mapNote = h('p', { id: 'map-note', class: 'hint' });
    const table = detectionsTable(feats);
    const scoresBox = h('div', { id: 'scores-box' });
    box.replaceChildren(
      h('h3', {}, 'Outputs'), linkList, scoresBox,
      h('h3', { id: 'det-h' }, `Detections (${feats.length})`),
      mapEl, mapNote, table);
    loadScores(id, links, scoresBox);  // beside the map, not before it
    await buildMap(id, mapEl, mapNote, feats, links, jobUrl);
    if (current.id !== id || !(hasAis(feats) || links.ais_unmatched)) return;
    const nUnmatched = await addUnmatched(id, links, mapNote);
    if (current.id !== id) return;
    mapNote.after(aisLegend(feats, nUnmatched));
  }

  /** Scores first, in this order; then any other number of the scores document. */
  const SCORE_KEYS = ['n_truth', 'n_detections', 'n_hit', 'n_missed', 'n_false', 'pd', 'precision', 'f1', 'fom'];

  /** The scores against the scene's ground truth (the metrics document's ``scores``, present
   * only when the scene has a truth file); nothing shown when there is none. */
  async function loadScores(id, links, el) {
    if (!links.metrics || !links.metrics.href) return;
    let met;
    try {
      met = await getJSON(links.metrics.href);
    } catch (e) {
      if (current.id !== id) return;
      const p = h('div', { class: 'problem', role: 'alert' });
      showProblem(p, e);
      el.replaceChildren(h('h3', {}, 'Scores'), p);
      return;
    }
    if (current.id !== id || !met || typeof met.scores !== 'object' || met.scores === null) return;
    const sc = met.scores;
    const head = h('h3', { id: 'scores-h' }, 'Scores against the ground truth');
    if (sc.error) {
      const p = h('div', { class: 'problem', id: 'scores-error' });
      showProblem(p, new ApiError('', 'scores unavailable', String(sc.error)));
      el.replaceChildren(head, p);
      return;
    }
    const nums = Object.keys(sc).filter((k) => typeof sc[k] === 'number');
    const order = SCORE_KEYS.filter((k) => nums.includes(k)).concat(nums.filter((k) => !SCORE_KEYS.includes(k)));
    const dl = h('dl', { class: 'kv scores', id: 'scores' });
    dl.replaceChildren(...order.flatMap((k) => [h('dt', {}, k), h('dd', { dataset: { key: k } }, fmtNum(sc[k]))]));
    const truth = typeof sc.truth === 'string' ? h('p', { class: 'hint' }, `truth: ${sc.truth.split('/').pop()}`) : null;
    el.replaceChildren(head, dl, truth);
  }

  function detectionsTable(feats) {
    if (!feats.length) return h('p', { class: 'hint', id: 'det-none' }, 'No detections.');
    const shown = feats.slice(0, MAX_ROWS);
    // a georeferenced scene: every detection has its WGS84 centre
    const geo = feats.every((f) => Array.isArray(f.properties.centroid_lonlat) && f.properties.centroid_lonlat.length === 2);
    const ais = hasAis(feats);
    const tbody = h('tbody', {}, shown.map((f, i) => {
      const p = f.properties;
      const [r0, c0, r1, c1] = p.bbox_px;
      const cen = Array.isArray(p.centroid_px) ? p.centroid_px : [(r0 + r1) / 2, (c0 + c1) / 2];
      const ll = geo ? p.centroid_lonlat : null;
      const len = p.length_m !== null && p.length_m !== undefined ? `${fmtNum(p.length_m, 3)} m` : (p.length_px !== undefined ? `${fmtNum(p.length_px, 3)} px` : '');
      const wid = p.width_m !== null && p.width_m !== undefined ? `${fmtNum(p.width_m, 3)} m` : (p.width_px !== undefined ? `${fmtNum(p.width_px, 3)} px` : '');
      const tr = h('tr', { dataset: { det: i } },
        h('td', {}, h('button', { type: 'button', class: 'small det-go', 'aria-label': `Show detection ${i + 1} on the map`, onclick: () => selectDet(i, true) }, String(i + 1))),
        h('td', {}, ll ? `${fmtLat(ll[1])}, ${fmtLon(ll[0])}` : `${fmtNum(cen[0], 5)}, ${fmtNum(cen[1], 5)}`),
        h('td', {}, `${r1 - r0}×${c1 - c0}`),
        h('td', { class: 'num' }, fmtNum(p.area_px)),
        h('td', { class: 'num' }, len), h('td', { class: 'num' }, wid),
        h('td', { class: 'num' }, fmtNum(p.score)), h('td', { class: 'num' }, fmtNum(p.peak)),
        ais ? aisCell(p) : null);
      if (ais) tr.dataset.ais = aisState(p);
      tr.addEventListener('click', (ev) => { if (!ev.target.closest('button')) selectDet(i, true); });
      return tr;
    }));
    const wrap = h('div', { class: 'scroll det-scroll' }, h('table', { id: 'det-table' },
      h('caption', { class: 'sr-only' }, 'Detections; choose one to show it on the map'),
      h('thead', {}, h('tr', {}, ['#', geo ? 'centre (lat, lon)' : 'centroid (row, col)', 'box (rows×cols)', 'area px', 'length', 'width', 'score', 'peak']
        .concat(ais ? ['AIS vessel'] : []).map((t) => h('th', { scope: 'col' }, t)))), tbody));
    const out = [wrap];
    if (feats.length > shown.length) out.push(h('p', { class: 'hint' }, `The first ${MAX_ROWS} of ${feats.length} are listed; all are drawn.`));
    return h('div', {}, out);
  }

  const BOX = { color: '#ffd400', weight: 2, fillOpacity: 0.08 };
  const BOX_SEL = { color: '#00e5ff', weight: 3, fillOpacity: 0.2 };

  // ---------------------------------------------------------------- AIS (docs/ais.md)

  /** Colours of a detection's AIS state (the legend's swatches use the same, app.css): matched
   * to a vessel's AIS, dark (no AIS though the AIS covers the scene), or none / unknown. */
  const AIS_COLOURS = { matched: '#2ee06f', dark: '#ff3b30', none: BOX.color };
  const AIS_LABELS = {
    matched: 'matched to AIS',
    dark: 'dark: no AIS though the AIS covers the scene',
    none: 'no AIS given, or unknown',
    unmatched: 'AIS vessel not matched to a detection',
  };
  /** A detection's AIS state from its ``ais`` and ``dark`` properties. */
  function aisState(p) {
    if (p && p.ais && typeof p.ais === 'object') return 'matched';
    if (p && p.dark === true) return 'dark';
    return 'none';
  }
  /** Whether the job's detections carry AIS results at all (a run given AIS files). */
  const hasAis = (feats) => feats.some((f) => 'ais' in f.properties || 'dark' in f.properties);
  /** A detection's box style: its AIS state's colour. */
  const boxStyle = (f) => ({ ...BOX, color: AIS_COLOURS[aisState(f.properties)] });
  /** The vessel's name and MMSI of a matched detection ('' otherwise). */
  function vesselText(p) {
    const a = p.ais;
    if (!a || typeof a !== 'object') return '';
    const name = typeof a.name === 'string' && a.name.trim() ? a.name.trim() : 'unnamed';
    return `${name} (MMSI ${a.mmsi})`;
  }
  /** The AIS cell of the detections table. */
  function aisCell(p) {
    const st = aisState(p);
    if (st === 'matched') {
      const d = typeof p.ais.distance_m === 'number' ? `, ${fmtNum(p.ais.distance_m, 3)} m off` : '';
      return h('td', { class: 'ais-matched', title: `score ${fmtNum(p.ais.score, 3)}${d}` }, vesselText(p));
    }
    if (st === 'dark') return h('td', { class: 'ais-dark' }, 'dark');
    return h('td', { class: 'ais-none' }, p.dark === null ? 'AIS does not cover' : '—');
  }
  /** The tooltip of detection i: its number, and its vessel or "dark". */
  function detLabel(f, i) {
    const st = aisState(f.properties);
    const extra = st === 'matched' ? ` · ${vesselText(f.properties)}` : (st === 'dark' ? ' · dark (no AIS)' : '');
    return `#${i + 1}${extra}`;
  }

  /** The legend of the AIS colours (only for a job whose detections carry AIS results). */
  function aisLegend(feats, nUnmatched) {
    const n = { matched: 0, dark: 0, none: 0 };
    for (const f of feats) n[aisState(f.properties)] += 1;
    const item = (k, count) => h('li', { dataset: { state: k } },
      h('span', { class: `swatch swatch-${k}`, 'aria-hidden': 'true' }), ` ${AIS_LABELS[k]}: `, h('b', {}, String(count)));
    const items = ['matched', 'dark', 'none'].map((k) => item(k, n[k]));
    if (nUnmatched !== null) items.push(item('unmatched', nUnmatched));
    return h('ul', { class: 'ais-legend', id: 'ais-legend', 'aria-label': 'AIS legend' }, items);
  }

  /** The AIS vessels that reported inside the footprint and matched no detection (the
   * results' ``ais_unmatched`` link, when the service gives it), as markers on a lon/lat map;
   * their count, or null when there is no such link or it cannot be read. */
  async function addUnmatched(id, links, note) {
    const link = links.ais_unmatched;
    if (!link || !link.href) return null;
    let fc;
    try {
      fc = await getJSON(link.href);
    } catch (e) {
      note.textContent += ' The unmatched AIS vessels could not be loaded.';
      return null;
    }
    if (current.id !== id) return null;
    const pts = (fc.features || []).filter((f) => f && f.geometry && f.geometry.type === 'Point'
      && Array.isArray(f.geometry.coordinates));
    if (current.map && document.getElementById('map').dataset.crs === 'EPSG:3857') {
      for (const f of pts) {
        const [lon, lat] = f.geometry.coordinates;
        const p = f.properties || {};
        const name = typeof p.name === 'string' && p.name.trim() ? p.name.trim() : 'unnamed';
        const len = typeof p.length_m === 'number' ? `, ${fmtNum(p.length_m, 3)} m` : '';
        L.circleMarker([lat, lon], { radius: 6, color: '#d200ff', weight: 2, fillOpacity: 0.3, className: 'ais-unmatched' })
          .bindTooltip(h('span', {}, `${name} (MMSI ${p.mmsi})${len}: not matched`), { direction: 'top' })
          .addTo(current.map);
      }
    }
    return pts.length;
  }

  /** A Leaflet tile layer; with a token, tiles are fetched with it (an <img> cannot send
   * Authorization, and reads may be protected) and shown from blob: URLs. */
  function tileLayer(url, opts) {
    if (!token()) return L.tileLayer(url, opts);
    const Layer = L.TileLayer.extend({
      createTile(coords, done) {
        const img = document.createElement('img');
        img.alt = '';
        img.setAttribute('role', 'presentation');
        fetch(this.getTileUrl(coords), { headers: authHeaders() })
          .then((r) => { if (!r.ok) throw new Error(`tile: HTTP ${r.status}`); return r.blob(); })
          .then((b) => {
            const u = URL.createObjectURL(b);
            img.onload = () => { URL.revokeObjectURL(u); done(null, img); };
            img.onerror = () => { URL.revokeObjectURL(u); done(new Error('tile: not an image'), img); };
            img.src = u;
          })
          .catch((e) => done(e, img));
        return img;
      },
    });
    return new Layer(url, opts);
  }

  /** The job's map: in lon/lat (Web Mercator, graticule) when the tiles' TileJSON carries the
   * scene's lon/lat grid (a georeferenced scene), else over the scene's pixel grid. */
  async function buildMap(id, el, note, feats, links, jobUrl) {
    if (typeof window.L === 'undefined') { note.textContent = 'The map library did not load.'; return; }
    let tj = null;
    let H;
    let W;
    try {
      tj = await getJSON(jobUrl('tiles.json'));
      H = tj.height; W = tj.width;
    } catch (e) {
      tj = null;  // no tiles for this job: fall back on the quicklook image
      try {
        const met = links.metrics ? await getJSON(links.metrics.href) : null;
        [H, W] = (met && met.scene && met.scene.shape) || [];
      } catch (e2) { /* no shape: no map */ }
    }
    if (current.id !== id) return;
    if (!H || !W) { note.textContent = 'No quicklook for this job.'; el.hidden = true; return; }
    const grid = tj && lonLatGrid(tj.lonlat, H, W);
    if (grid) buildGeoMap(el, note, feats, tj, grid);
    else buildPixelMap(el, note, feats, tj, H, W, jobUrl);
    finishMap(el);
  }

  /** Common end of both maps: the zoom in data-zoom (tests and styles read it), ready. */
  function finishMap(el) {
    const map = current.map;
    map.on('zoomend', () => { el.dataset.zoom = String(map.getZoom()); });
    el.dataset.zoom = String(map.getZoom());
    el.dataset.ready = 'true';
  }

  /** A small box in the map's corner showing the position under the pointer. */
  function cursorControl(map, text) {
    const Ctl = L.Control.extend({
      onAdd() {
        const div = L.DomUtil.create('div', 'map-cursor');
        div.id = 'map-cursor';
        div.setAttribute('aria-live', 'off');
        div.textContent = '';
        map.on('mousemove', (ev) => { div.textContent = text(ev.latlng); });
        map.on('mouseout', () => { div.textContent = ''; });
        return div;
      },
    });
    new Ctl({ position: 'bottomleft' }).addTo(map);
  }

  /** Leaflet map over the scene's pixel grid (CRS.Simple): map pixels at zoom Z are scene pixels. */
  function buildPixelMap(el, note, feats, tj, H, W, jobUrl) {
    const Z = tj ? tj.maxzoom : nativeZoom(H, W);
    const map = L.map(el, {
      crs: L.CRS.Simple, minZoom: 0, maxZoom: Z + 2, attributionControl: false, zoomSnap: 0.5,
      preferCanvas: feats.length > 2000,
    });
    current.map = map;
    el.dataset.crs = 'pixels';
    const px = (r, c) => map.unproject([c, r], Z);
    const bounds = L.latLngBounds(px(H, 0), px(0, W));
    if (tj) {
      const tiles = tileLayer(safeHref(tj.tiles[0]).replace(/%7B/g, '{').replace(/%7D/g, '}'), {
        tileSize: tj.tileSize || 256, minZoom: 0, minNativeZoom: tj.minzoom || 0, maxNativeZoom: Z, maxZoom: Z + 2,
        noWrap: true, bounds, keepBuffer: 1,
      });
      let failed = 0;
      tiles.on('tileerror', () => { failed += 1; note.textContent = `${failed} tile(s) failed to load.`; });
      tiles.addTo(map);
    } else {
      const step = Math.max(1, Math.ceil(Math.max(H, W) / 1024));
      L.imageOverlay(jobUrl('preview.png?size=1024'), L.latLngBounds(px(Math.ceil(H / step) * step, 0),
        px(0, Math.ceil(W / step) * step)), { alt: 'scene quicklook' }).addTo(map);
      note.textContent = 'Map tiles are not available for this job: showing the quicklook image.';
    }
    map.setMaxBounds(bounds.pad(0.5));
    current.boxes = feats.map((f, i) => {
      const [r0, c0, r1, c1] = f.properties.bbox_px;
      return detBox(L.rectangle(L.latLngBounds(px(r1, c0), px(r0, c1)), { ...boxStyle(f), className: `det-box det-${aisState(f.properties)}` }), i, f);
    });
    current.feats = feats;
    current.focus = (f) => {
      const [r0, c0, r1, c1] = f.properties.bbox_px;
      const m = Math.max(24, r1 - r0, c1 - c0);
      return [L.latLngBounds(px(r1 + m, c0 - m), px(r0 - m, c1 + m)), Z + 2];
    };
    cursorControl(map, (ll) => {
      const p = map.project(ll, Z);
      return (p.y < 0 || p.x < 0 || p.y > H || p.x > W) ? '' : `row ${Math.floor(p.y)}, col ${Math.floor(p.x)}`;
    });
    map.fitBounds(bounds);
  }

  function detBox(layer, i, f) {
    layer.bindTooltip(h('span', {}, detLabel(f, i)), { direction: 'top' });
    layer.on('click', () => selectDet(i, false));
    layer.addTo(current.map);
    const el = layer.getElement && layer.getElement();  // (none on a canvas: many detections)
    if (el) el.dataset.det = String(i);
    return layer;
  }

  // ---------------------------------------------------------------- lon/lat map

  const fmtDeg = (v, pos, neg, d = 5) => `${Math.abs(v).toFixed(d)}° ${v >= 0 ? pos : neg}`;
  const fmtLat = (v, d) => fmtDeg(v, 'N', 'S', d);
  const fmtLon = (v, d) => fmtDeg(((v + 540) % 360) - 180, 'E', 'W', d);

  /** The scene's pixel -> lon/lat map from TileJSON's ``lonlat`` grid (nodes at rows
   * 0, H/n, ..., H and columns 0, W/n, ..., W): bilinear inside a cell, extended linearly past
   * the edges. null when the grid is absent or malformed. */
  function lonLatGrid(g, H, W) {
    if (!g || !Array.isArray(g.lon) || !Array.isArray(g.lat) || !Array.isArray(g.rows) || !Array.isArray(g.cols)) return null;
    const n = g.rows.length - 1;
    const m = g.cols.length - 1;
    const ok = (a) => a.length === n + 1 && a.every((row) => Array.isArray(row) && row.length === m + 1
      && row.every((v) => typeof v === 'number' && Number.isFinite(v)));
    if (n < 1 || m < 1 || !ok(g.lon) || !ok(g.lat)) return null;
    const at = (r, c) => {
      const fi = (r / H) * n;
      const fj = (c / W) * m;
      const i = Math.max(0, Math.min(n - 1, Math.floor(fi)));
      const j = Math.max(0, Math.min(m - 1, Math.floor(fj)));
      const u = fi - i;
      const v = fj - j;
      const bl = (a) => (1 - u) * ((1 - v) * a[i][j] + v * a[i][j + 1]) + u * ((1 - v) * a[i + 1][j] + v * a[i + 1][j + 1]);
      return L.latLng(bl(g.lat), bl(g.lon));
    };
    const border = [];
    for (let j = 0; j <= m; j++) border.push(L.latLng(g.lat[0][j], g.lon[0][j]));
    for (let i = 1; i <= n; i++) border.push(L.latLng(g.lat[i][m], g.lon[i][m]));
    for (let j = m - 1; j >= 0; j--) border.push(L.latLng(g.lat[n][j], g.lon[n][j]));
    for (let i = n - 1; i > 0; i--) border.push(L.latLng(g.lat[i][0], g.lon[i][0]));
    return { at, border, bounds: L.latLngBounds(border), method: g.method };
  }

  /** The CSS matrix3d drawing a size x size image onto the quadrilateral q (layer points of its
   * corners: top-left, top-right, bottom-right, bottom-left): the projective map of the unit
   * square onto q (Heckbert, "Fundamentals of texture mapping", 1989, sec. 2.2.3). */
  function quadMatrix(q, size) {
    const [p0, p1, p2, p3] = q;
    const dx1 = p1.x - p2.x; const dx2 = p3.x - p2.x; const dx3 = p0.x - p1.x + p2.x - p3.x;
    const dy1 = p1.y - p2.y; const dy2 = p3.y - p2.y; const dy3 = p0.y - p1.y + p2.y - p3.y;
    const det = dx1 * dy2 - dx2 * dy1;
    const g = det ? (dx3 * dy2 - dx2 * dy3) / det : 0;
    const k = det ? (dx1 * dy3 - dx3 * dy1) / det : 0;
    const a = p1.x - p0.x + g * p1.x; const b = p3.x - p0.x + k * p3.x;
    const d = p1.y - p0.y + g * p1.y; const e = p3.y - p0.y + k * p3.y;
    const s = 1 / size;
    return `matrix3d(${a * s},${d * s},0,${g * s},${b * s},${e * s},0,${k * s},0,0,1,0,${p0.x},${p0.y},0,1)`;
  }

  /** The quicklook tiles (XYZ over the scene's pixel grid) drawn in the map's projection: at
   * each view, the tile level whose pixels are about screen pixels, each visible tile warped
   * onto its four corners' map position (lon/lat from the grid). */
  const WarpedTiles = L.Layer.extend({
    initialize(url, tj, grid, note) {
      this.url = url; this.tj = tj; this.grid = grid; this.note = note;
      this.imgs = new Map();
      this.failed = 0;
    },
    getEvents() {
      return { zoom: this.place, viewreset: this.update, zoomend: this.update, moveend: this.update, resize: this.update };
    },
    onAdd(map) {
      this.box = L.DomUtil.create('div', 'warp-tiles', map.getPane('tilePane'));
      this.update();
    },
    onRemove() {
      this.box.remove();
      this.imgs.clear();
    },
    /** During a zoom (a fly to a detection): the tiles shown so far, moved to their places. */
    place() {
      const map = this._map;
      for (const img of this.imgs.values()) img.style.transform = quadMatrix(img.corners.map((ll) => map.latLngToLayerPoint(ll)), img.width);
    },
    update() {
      const map = this._map;
      const { height: H, width: W, maxzoom: Z } = this.tj;
      const T = this.tj.tileSize || 256;
      const at = this.grid.at;
      const lp = (r, c) => map.latLngToLayerPoint(at(r, c));
      const perPx = lp(0, 0).distanceTo(lp(H, W)) / Math.hypot(H, W);  // screen px per scene px
      const z = Math.max(0, Math.min(Z, Math.round(Z + Math.log2(perPx))));
      const s = T * 2 ** (Z - z);
      const view = map.getBounds().pad(0.2);
      const keep = new Set();
      for (let y = 0; y * s < H; y++) {
        for (let x = 0; x * s < W; x++) {
          const r0 = y * s; const c0 = x * s;
          const corners = [at(r0, c0), at(r0, c0 + s), at(r0 + s, c0 + s), at(r0 + s, c0)];
          if (!L.latLngBounds(corners).intersects(view)) continue;
          const key = `${z}/${x}/${y}`;
          keep.add(key);
          let img = this.imgs.get(key);
          if (!img) {
            img = this.tile(this.url.replace('{z}', z).replace('{x}', x).replace('{y}', y), T);
            this.imgs.set(key, img);
            this.box.append(img);
          }
          img.corners = corners;
          img.style.transform = quadMatrix(corners.map((ll) => map.latLngToLayerPoint(ll)), T);
        }
      }
      for (const [key, img] of this.imgs) if (!keep.has(key)) { img.remove(); this.imgs.delete(key); }
      this.box.dataset.level = String(z);
    },
    tile(url, T) {
      const img = document.createElement('img');
      img.alt = '';
      img.setAttribute('role', 'presentation');
      img.className = 'warp-tile';
      img.width = T;
      img.height = T;
      img.onload = () => img.classList.add('loaded');
      img.onerror = () => { this.failed += 1; this.note.textContent = `${this.failed} tile(s) failed to load.`; };
      if (!token()) { img.src = url; return img; }
      fetch(url, { headers: authHeaders() })  // reads may need the token: an <img> cannot send it
        .then((r) => { if (!r.ok) throw new Error(`tile: HTTP ${r.status}`); return r.blob(); })
        .then((b) => {
          const u = URL.createObjectURL(b);
          img.addEventListener('load', () => URL.revokeObjectURL(u), { once: true });
          img.src = u;
        })
        .catch(() => img.onerror());
      return img;
    },
  });

  /** Graticule step (degrees) giving about 3 to 7 lines across a span of `span` degrees. */
  function gratStep(span) {
    const steps = [30, 20, 10, 5, 2, 1, 0.5, 0.2, 0.1, 0.05, 0.02, 0.01, 0.005, 0.002, 0.001, 0.0005, 0.0002, 0.0001];
    return steps.find((st) => span / st >= 3) || steps[steps.length - 1];
  }

  /** A lon/lat graticule with its values labelled on the map's left (latitude) and top
   * (longitude) edges, redrawn as the view moves. */
  const Graticule = L.Layer.extend({
    onAdd(map) {
      this.lines = L.layerGroup().addTo(map);
      this.labels = L.DomUtil.create('div', 'grat-labels', map.getContainer());
      map.on('move zoomend resize', this.update, this);
      this.update();
    },
    onRemove(map) {
      map.off('move zoomend resize', this.update, this);
      this.lines.remove();
      this.labels.remove();
    },
    update() {
      const map = this._map;
      const b = map.getBounds();
      const size = map.getSize();
      const stLon = gratStep(b.getEast() - b.getWest());
      const stLat = gratStep(b.getNorth() - b.getSouth());
      const dec = (st) => Math.max(0, Math.ceil(-Math.log10(st) - 1e-9));
      this.lines.clearLayers();
      const kids = [];
      const style = { color: '#9fd3ff', weight: 1, opacity: 0.55, interactive: false, className: 'graticule' };
      for (let lon = Math.ceil(b.getWest() / stLon) * stLon; lon <= b.getEast(); lon += stLon) {
        this.lines.addLayer(L.polyline([[b.getSouth(), lon], [b.getNorth(), lon]], style));
        const x = map.latLngToContainerPoint([b.getNorth(), lon]).x;
        if (x > 60 && x < size.x - 60) {  // clear of the corners (and of the zoom buttons)
          kids.push(h('span', { class: 'grat-label grat-lon', dataset: { lon: lon.toFixed(6) } }, fmtLon(lon, dec(stLon))));
          kids[kids.length - 1].style.left = `${x}px`;
        }
      }
      for (let lat = Math.ceil(b.getSouth() / stLat) * stLat; lat <= b.getNorth(); lat += stLat) {
        this.lines.addLayer(L.polyline([[lat, b.getWest()], [lat, b.getEast()]], style));
        const y = map.latLngToContainerPoint([lat, b.getWest()]).y;
        if (y > 20 && y < size.y - 20) {
          kids.push(h('span', { class: 'grat-label grat-lat', dataset: { lat: lat.toFixed(6) } }, fmtLat(lat, dec(stLat))));
          kids[kids.length - 1].style.top = `${y}px`;
        }
      }
      this.labels.replaceChildren(...kids);
    },
  });

  /** The scene in lon/lat: a Web Mercator map (EPSG:3857, no basemap: offline) with the
   * quicklook tiles warped into place, the scene's outline, a lon/lat graticule with labelled
   * edges, a scale bar, the detections drawn from their WGS84 outlines and the pointer's lon/lat. */
  function buildGeoMap(el, note, feats, tj, grid) {
    const map = L.map(el, {
      crs: L.CRS.EPSG3857, attributionControl: false, zoomSnap: 0.5, zoomAnimation: false,
      maxZoom: 22, preferCanvas: feats.length > 2000, zoomControl: false,
    });
    L.control.zoom({ position: 'topright' }).addTo(map);  // the left and top edges carry the graticule's labels
    current.map = map;
    el.dataset.crs = 'EPSG:3857';
    el.classList.add('geo');
    map.fitBounds(grid.bounds);
    const url = safeHref(tj.tiles[0]).replace(/%7B/g, '{').replace(/%7D/g, '}');
    new WarpedTiles(url, tj, grid, note).addTo(map);
    L.polygon(grid.border, { color: '#9fd3ff', weight: 1, fill: false, interactive: false, className: 'scene-outline' }).addTo(map);
    new Graticule().addTo(map);
    L.control.scale({ imperial: false, position: 'bottomright' }).addTo(map);
    map.setMaxBounds(grid.bounds.pad(1));
    const pixelRing = (f) => {  // a detection without an outline: its pixel box through the grid
      const [r0, c0, r1, c1] = f.properties.bbox_px;
      return [grid.at(r0, c0), grid.at(r0, c1), grid.at(r1, c1), grid.at(r1, c0)];
    };
    const ring = (f) => {
      const g = f.geometry;
      if (g && g.type === 'Polygon' && Array.isArray(g.coordinates) && Array.isArray(g.coordinates[0])) {
        return g.coordinates[0].map(([lon, lat]) => L.latLng(lat, lon));
      }
      return pixelRing(f);
    };
    current.boxes = feats.map((f, i) => detBox(L.polygon(ring(f), { ...boxStyle(f), className: `det-box det-${aisState(f.properties)}` }), i, f));
    current.feats = feats;
    current.focus = (f) => [L.latLngBounds(ring(f)).pad(2), 20];
    cursorControl(map, (ll) => `${fmtLat(ll.lat)}, ${fmtLon(ll.lng)}`);
    note.textContent = `Web Mercator map (EPSG:3857) of the scene's WGS84 position (${grid.method || 'georeferenced'}); `
      + 'no basemap. The pointer shows longitude and latitude.';
  }

  /** Highlight detection i in the table and on the map; pan/zoom to it when asked. */
  function selectDet(i, zoom) {
    if (!current.boxes) return;
    if (current.sel !== undefined && current.boxes[current.sel]) current.boxes[current.sel].setStyle(boxStyle(current.feats[current.sel]));
    current.sel = i;
    const rect = current.boxes[i];
    rect.setStyle(BOX_SEL);
    rect.bringToFront();
    for (const tr of document.querySelectorAll('#det-table tbody tr')) {
      const on = Number(tr.dataset.det) === i;
      tr.classList.toggle('selected', on);
      if (on) tr.setAttribute('aria-current', 'true'); else tr.removeAttribute('aria-current');
      if (on && !zoom) tr.scrollIntoView({ block: 'nearest' });
    }
    if (zoom) {
      const [b, maxZoom] = current.focus(current.feats[i]);
      current.map.flyToBounds(b, { maxZoom, duration: 0.4 });
    }
  }

  // ---------------------------------------------------------------- ingest panel

  let ingestTimer = null;

  async function pollIngest() {
    clearTimeout(ingestTimer);
    const body = $('ingest-body');
    let doc;
    try {
      doc = await getJSON(api('ingest'));
    } catch (e) {
      ingestKey = '';
      if (e instanceof ApiError && e.status === 404) {
        body.replaceChildren(h('p', { id: 'ingest-state' }, 'Scheduled ingest is not configured.'));
      } else {
        const p = h('div', { class: 'problem', role: 'alert' });
        showProblem(p, e);
        body.replaceChildren(p);
        if (!document.hidden) ingestTimer = setTimeout(pollIngest, INGEST_MS * 4);
      }
      return;
    }
    renderIngest(doc || {});
    const busy = doc && (doc.backlog > 0 || (doc.passes || []).some((p) => p.status === 'waiting' || p.status === 'ingesting'));
    if (doc && doc.enabled && !document.hidden) ingestTimer = setTimeout(pollIngest, busy ? FAST_MS * 1.5 : INGEST_MS);
  }

  let ingestActions = null;  // the Scan-now button and its message: kept across refreshes (focus stays)
  let ingestKey = '';

  function ingestButtons() {
    if (ingestActions) return ingestActions;
    const msg = h('span', { id: 'ingest-scan-msg', class: 'hint', role: 'status' });
    const btn = h('button', {
      type: 'button', id: 'ingest-scan', class: 'small',
      onclick: async () => {
        msg.textContent = '';
        try {
          await getJSON(api('ingest/scan'), { method: 'POST' });
          msg.textContent = ' scan requested';
          setTimeout(pollIngest, 1000);
        } catch (e) {
          msg.textContent = ` ${e instanceof ApiError ? `${e.status} ${e.title}: ${e.detail}` : e}`;
        }
      },
    }, 'Scan now');
    ingestActions = h('p', { class: 'ingest-actions' }, btn, msg);
    return ingestActions;
  }

  function renderIngest(d) {
    const body = $('ingest-body');
    const key = JSON.stringify(d);
    if (key === ingestKey) return;
    if (ingestKey) pollSoon();  // passes moved on: their ingest and detector jobs did too
    ingestKey = key;
    if (!d.enabled) {
      body.replaceChildren(h('p', { id: 'ingest-state' }, 'Scheduled ingest is not configured.'));
      return;
    }
    const sch = d.schedule || {};
    const schedule = [sch.interval_s ? `every ${sch.interval_s} s` : '', sch.cron ? `cron ${sch.cron} (UTC)` : '']
      .filter(Boolean).join('; ') || 'on new files';
    const dl = h('dl', { class: 'kv' });
    const counts = Object.entries(d.counts || {}).filter(([, n]) => n).map(([k, n]) => `${k} ${n}`).join(', ');
    kv(dl, [
      ['State', h('span', { id: 'ingest-state' }, 'enabled')],
      ['Inboxes', (d.inboxes || []).length ? h('ul', { class: 'plain' }, (d.inboxes || []).map((x) => h('li', {}, h('code', {}, x)))) : 'none'],
      ['Schedule', schedule], ['Leader', d.leader === null || d.leader === undefined ? 'none' : String(d.leader)],
      ['Last scan', fmtTime(d.last_scan) || 'never'], ['Next scan', fmtTime(d.next_scan) || ''],
      ['Backlog', h('span', { id: 'ingest-backlog' }, String(d.backlog ?? 0))], ['Passes', counts || 'none'],
    ]);
    const passes = (d.passes || []).slice(0, 25);  // newest first
    const info = [dl];
    if (passes.length) {
      info.push(h('div', { class: 'scroll' }, h('table', { id: 'ingest-table' },
        h('caption', { class: 'sr-only' }, 'Satellite passes seen by the ingest loop, newest first'),
        h('thead', {}, h('tr', {}, ['File', 'Status', 'Scene', 'Jobs', 'Updated'].map((t) => h('th', { scope: 'col' }, t)))),
        h('tbody', {}, passes.map((p) => h('tr', { dataset: { status: p.status || '' } },
          h('td', { class: 'c-msg', title: p.file || '' }, String(p.file || p.key || '').split('/').pop()),
          h('td', {}, statusBadge(p.status || ''), p.reason ? h('div', { class: 'hint reason' }, p.reason) : null),
          h('td', {}, p.sceneID || ''),
          h('td', {}, (p.ingestJob ? [p.ingestJob] : []).concat(p.jobs || []).map((jid) =>
            h('a', { href: `#/jobs/${encodeURIComponent(jid)}`, class: 'job-chip', title: jid }, String(jid).slice(0, 8)))),
          h('td', { class: 'c-created' }, fmtTime(p.updated || p.seen))))))));
    }
    let infoBox = $('ingest-info');
    if (!infoBox) {
      infoBox = h('div', { id: 'ingest-info' });
      body.replaceChildren(infoBox, ingestButtons());
    }
    infoBox.replaceChildren(...info);
  }

  // ---------------------------------------------------------------- start

  function refreshAll() {
    loadScenes();
    pollJobs();
    pollIngest();
  }

  document.addEventListener('visibilitychange', () => {
    if (!document.hidden) { pollJobs(); pollIngest(); }
  });
  window.addEventListener('hashchange', route);

  async function start() {
    initToken();
    initForm();
    initUpload();
    checkDashboard();
    route(null);
    pollJobs();
    pollIngest();
    await loadScenes();
    try {
      await loadProcesses();
    } catch (e) {
      showProblem($('submit-error'), e);
    }
    document.body.dataset.ready = 'true';
  }

  start();
})();
