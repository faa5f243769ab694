"""The console's pages (plain HTML and script, no build step, nothing fetched from elsewhere).

The operator's page: the trial queue; a live view per camera with the trial's reference layout overlaid (an
opacity slider, and the alignment figure: how closely the live view matches it, 100 = exactly); Reset scene,
Record layout, Start, Stop and E-stop (the button, or the Escape key anywhere on the page); the safety state
and counters, live over the WebSocket. The raters' pages: the trials that have run, by blind code, and one
trial's video and its task's rubric, scored under the name the rater's token was issued to. No page, nor
anything they load, names the policy.
"""

LOGIN_PAGE = """<!doctype html>
<html><head><meta charset="utf-8"><title>RealEval console: log in</title></head>
<body style="font-family: sans-serif; margin: 3em">
<h1>RoboDojo RealEval console</h1>
<p>This console needs a token: the operator's (printed by <code>dojo console</code> when it started) or a
rater's own (from <code>dojo console add-rater NAME</code>).</p>
<form method="post" action="/login"><input name="token" type="password" id="token" placeholder="token" autofocus>
<button type="submit" id="login">Log in</button></form>
</body></html>
"""

FORBIDDEN_PAGE = """<!doctype html>
<html><head><meta charset="utf-8"><title>RealEval console: not for raters</title></head>
<body style="font-family: sans-serif; margin: 3em">
<h1>403: not for raters</h1>
<p>A rater's token opens only the rater pages: <a href="/rate">the trials to rate</a>.</p>
</body></html>
"""

CONSOLE_PAGE = """<!doctype html>
<html><head><meta charset="utf-8"><title>RealEval console</title>
<style>
body { font-family: sans-serif; margin: 1em; }
table { border-collapse: collapse; } td, th { border: 1px solid #ccc; padding: 2px 8px; }
.views { display: flex; gap: 1em; flex-wrap: wrap; margin: 1em 0; }
.view { position: relative; } .view img { display: block; width: 320px; }
.view img.ref { position: absolute; top: 0; left: 0; }
#estop { background: #c00; color: white; font-size: 1.4em; font-weight: bold; padding: .4em 1.2em; }
#safety { font-weight: bold; } tr.current { background: #eef; }
</style></head>
<body>
<h1>RoboDojo RealEval console</h1>
<p>Safety: <span id="safety">?</span> &middot; step <span id="step">0</span> &middot;
arms from the reset pose: <span id="home">?</span> rad <span id="error" style="color:#c00"></span></p>
<p>Trial <b id="current">none</b>
<button id="reset">Reset scene</button> <button id="layout">Record layout</button>
<button id="start">Start</button> <button id="stop">Stop</button>
<button id="estop" title="Escape key">E-STOP</button>
&middot; overlay <input id="opacity" type="range" min="0" max="100" value="40"> &middot;
alignment <span id="alignment">-</span></p>
<div class="views" id="views"></div>
<h2>Safety counters (this trial)</h2><table id="counters"></table>
<h2>Trials</h2>
<table id="trials"><thead><tr><th>trial</th><th>task</th><th>#</th><th>status</th><th>ended</th>
<th>steps</th><th>video</th></tr></thead><tbody></tbody></table>
<script>
const cameras = new Set(); let current = null; let trials = []; let estopPort = null;
const $ = (id) => document.getElementById(id);
async function post(path) {
  const r = await fetch(path, {method: 'POST'});
  if (!r.ok) { $('error').textContent = (await r.json()).detail; } else { $('error').textContent = ''; }
}
function selected() {
  if (current && current.status !== 'done') return current.code;
  const next = trials.find(t => t.status === 'queued' || t.status === 'ready'); return next ? next.code : null;
}
async function refreshTrials() {
  trials = await (await fetch('/api/trials')).json();
  const body = $('trials').querySelector('tbody'); body.innerHTML = '';
  for (const t of trials) {
    const row = body.insertRow(); row.id = 'trial-' + t.code;
    if (current && current.code === t.code) row.className = 'current';
    for (const v of [t.code, t.task, t.trial, t.status, t.end_reason || '', t.steps]) row.insertCell().textContent = v;
    row.insertCell().innerHTML = t.video ? `<a class="video" href="/video/${t.code}.mp4">video</a>` : '';
  }
}
function ensureView(camera) {
  if (cameras.has(camera)) return; cameras.add(camera);
  const div = document.createElement('div'); div.className = 'view';
  div.innerHTML = `<div>${camera}</div><div style="position:relative"><img class="live" id="live-${camera}">` +
    `<img class="ref" id="ref-${camera}" style="opacity:.4" onerror="this.style.display='none'"></div>`;
  $('views').appendChild(div);
}
function refreshViews() {
  const code = selected(); const opacity = $('opacity').value / 100;
  for (const c of cameras) {
    $('live-' + c).src = `/camera/${c}.jpg?t=${Date.now()}`;
    const ref = $('ref-' + c);
    if (code) { const src = `/layout/${code}/${c}.png`; if (!ref.src.endsWith(src)) { ref.style.display = ''; ref.src = src; } }
    ref.style.opacity = opacity;
  }
}
async function refreshAlignment() {
  const code = selected(); if (!code) return;
  const a = await (await fetch(`/api/trials/${code}/alignment`)).json();
  const parts = Object.entries(a).map(([c, v]) => `${c} ${v}`); $('alignment').textContent = parts.join(', ') || '-';
}
function connect() {
  const ws = new WebSocket(`${location.protocol === 'https:' ? 'wss' : 'ws'}://${location.host}/ws/state`);
  ws.onmessage = (m) => {
    const s = JSON.parse(m.data); current = s.trial; estopPort = s.estop_port;
    $('safety').textContent = s.safety; $('step').textContent = s.step;
    $('home').textContent = s.from_reset_pose_rad ?? '?'; $('current').textContent = current ? current.code : 'none';
    if (s.error) $('error').textContent = s.error;
    $('counters').innerHTML = Object.entries(s.counters).map(([k, v]) => `<tr><td>${k}</td><td id="counter-${k}">${v}</td></tr>`).join('');
  };
  ws.onclose = () => setTimeout(connect, 1000);
}
$('reset').onclick = () => { const c = selected(); if (c) post(`/api/trials/${c}/reset`); };
$('layout').onclick = () => { const c = selected(); if (c) post(`/api/trials/${c}/layout`); };
$('start').onclick = () => { const c = selected(); if (c) post(`/api/trials/${c}/start`); };
$('stop').onclick = () => post('/api/stop');
async function estop() {  // to the e-stop's own process when there is one (it holds without this server)
  if (estopPort) {
    try {
      const r = await fetch(`${location.protocol}//${location.hostname}:${estopPort}/estop`, {method: 'POST', credentials: 'include'});
      if (r.ok) { $('error').textContent = ''; return; }
    } catch (e) { /* not answering: the console's own e-stop below */ }
  }
  post('/api/estop');
}
$('estop').onclick = estop;
document.addEventListener('keydown', (e) => { if (e.key === 'Escape') { e.preventDefault(); estop(); } });
fetch('/api/state').then(r => r.json()).then(s => { for (const c of s.cameras || []) ensureView(c); });
connect(); refreshTrials();
setInterval(refreshTrials, 1000); setInterval(refreshViews, 300); setInterval(refreshAlignment, 1000);
</script>
</body></html>
"""

RATERS_PAGE = """<!doctype html>
<html><head><meta charset="utf-8"><title>RealEval: trials to rate</title>
<style>body { font-family: sans-serif; margin: 1em; } td, th { border: 1px solid #ccc; padding: 2px 8px; }
table { border-collapse: collapse; }</style></head>
<body>
<h1>Trials to rate</h1>
<p>Rating as <b id="rater"></b></p>
<table id="trials"><thead><tr><th>trial</th><th>task</th><th>your rating</th></tr></thead><tbody></tbody></table>
<script>
fetch('/api/rater/trials').then(r => r.json()).then(r => {
  document.getElementById('rater').textContent = r.rater;
  const body = document.querySelector('#trials tbody');
  for (const t of r.trials) {
    const row = body.insertRow(); row.id = 'trial-' + t.code;
    row.insertCell().innerHTML = `<a class="rate" href="/rate/${t.code}">${t.code}</a>`;
    row.insertCell().textContent = t.task; row.insertCell().textContent = t.rated ? 'done' : 'to do';
  }
});
</script>
</body></html>
"""

RATER_PAGE = """<!doctype html>
<html><head><meta charset="utf-8"><title>RealEval: rate a trial</title>
<style>body { font-family: sans-serif; margin: 1em; } video { width: 960px; }</style></head>
<body>
<h1>Rate trial <span id="code"></span></h1>
<p><a href="/rate">all trials</a> &middot; rating as <b id="rater"></b></p>
<p id="instruction"></p>
<video id="video" controls muted></video>
<form id="rating">
<fieldset><legend>Rubric: stages reached</legend><div id="stages"></div></fieldset>
<p><label><input type="checkbox" id="success"> the task succeeded</label></p>
<button type="submit" id="submit">Submit rating</button>
</form>
<p id="verdict"></p>
<script>
const code = location.pathname.split('/').pop(); const $ = (id) => document.getElementById(id);
$('code').textContent = code; $('video').src = `/video/${code}.mp4`;
fetch(`/api/trials/${code}/rubric`).then(r => r.json()).then(r => {
  $('instruction').textContent = 'Instruction: ' + r.instruction; $('rater').textContent = r.rater || '';
  $('stages').innerHTML = r.stages.map(s => `<label><input type="checkbox" class="stage" name="${s.name}"> ${s.name} (weight ${s.weight})</label><br>`).join('');
});
$('rating').onsubmit = async (e) => {
  e.preventDefault();
  const stages = {}; for (const box of document.querySelectorAll('.stage')) stages[box.name] = box.checked;
  const r = await fetch(`/api/trials/${code}/ratings`, {method: 'POST', headers: {'Content-Type': 'application/json'},
    body: JSON.stringify({success: $('success').checked, stages})});
  const v = await r.json();
  $('verdict').textContent = !r.ok ? v.detail : v.flagged ? `flagged for adjudication: ${v.reason}` :
    v.settled ? `settled: success ${v.success}, score ${v.score.toFixed(1)}` : `recorded (${v.reason})`;
};
</script>
</body></html>
"""
