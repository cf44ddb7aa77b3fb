"""``viewer.html``: the side-by-side image viewer `bench` writes next to its report (no network).

For every frame: the reference, the input and every method, with synchronized pan (drag) and zoom
(wheel), an exposure control acting on the HDR radiance, a toggle between images and per-pixel
error maps (relative squared error ``(x - ref)^2 / (ref^2 + 0.01)``, averaged over channels, in false
colour on a log scale with a legend), keyboard switching (left / right: method in the large view,
up / down: frame, ``e``: error maps), and each image's RelMSE / SSIM / time from the report. Frames
of a sequence play as a video (space) with the method's temporal error shown. A method that failed
on a frame is shown as a panel with its reason.

Images travel as half floats (``float16``, little endian, RGB), base64 encoded, decoded by the page:
the exposure control works on radiance, not on 8-bit pixels. Up to ``max_mib`` (50 MiB) everything is
inlined into one self-contained file; beyond it each image is a small script in
``viewer_images/`` beside the page (script files load from ``file://`` where ``fetch`` would not).
``#selftest`` in the page's URL runs its own checks (every image decoded, switching methods changes
the displayed pixels, the numbers shown equal the report's) and writes the result and any
JavaScript error into ``<pre id="selftest">`` (the browser test reads it).
"""
from __future__ import annotations

import base64
import hashlib
import json
import os
import shutil
from pathlib import Path

import numpy as np

from .fsutil import write_text

__all__ = ["ImageStore", "write_viewer", "MAX_MIB"]

MAX_MIB = 50.0
IMAGES_DIR = "viewer_images"


def encode(image: np.ndarray) -> dict:
    """An HDR image as the page reads it: float16 RGB, base64."""
    a = np.asarray(image, np.float32)[..., :3]
    a = np.nan_to_num(a, nan=0.0, posinf=65504.0, neginf=-65504.0).clip(-65504, 65504).astype("<f2")
    return {"w": int(a.shape[1]), "h": int(a.shape[0]), "data": base64.b64encode(a.tobytes()).decode("ascii")}


class ImageStore:
    """Collects the images of a bench run (ids -> encoded) without keeping float32 copies."""

    def __init__(self) -> None:
        self.images: dict[str, dict] = {}

    def add(self, key: str, image: np.ndarray) -> str:
        if key not in self.images:
            self.images[key] = encode(image)
        return key

    def nbytes(self) -> int:
        return sum(len(v["data"]) for v in self.images.values())


def write_viewer(report: dict, store: ImageStore, out_dir: str | os.PathLike, *, max_mib: float = MAX_MIB) -> Path:
    """Write ``viewer.html`` (and ``viewer_images/`` when over ``max_mib``) for a bench report whose
    records carry ``image`` / ``reference`` / ``input`` ids into ``store``."""
    out_dir = Path(out_dir)
    frames: dict[str, dict] = {}
    for r in report["records"]:
        f = frames.setdefault(r["file"], {"file": r["file"], "shot": r["shot"], "spp": r["spp"],
                                          "sequence": r.get("sequence"), "frame": r.get("frame"),
                                          "reference": r.get("reference_image"), "methods": []})
        f["methods"].append({"method": r["method"], "image": r.get("image_id"), "relmse": r["relmse"],
                             "ssim": r["ssim"], "seconds": r["seconds"], "notes": r.get("notes", [])})
    for s in report.get("skipped", []):
        if "file" in s and s["file"] in frames:
            frames[s["file"]]["methods"].append({"method": s["method"], "image": None, "failed": s["reason"]})
    temporal = {f"{t['sequence']}|{t['render']}|{t['method']}": t["temporal_error"] for t in report.get("temporal", [])}
    inline = store.nbytes() <= max_mib * 2**20
    images_dir = out_dir / IMAGES_DIR
    if images_dir.exists():
        shutil.rmtree(images_dir)
    scripts = ""
    if inline:
        payload = json.dumps(store.images)
    else:
        images_dir.mkdir(parents=True)
        for key, img in store.images.items():
            name = hashlib.sha1(key.encode()).hexdigest()[:16] + ".js"
            write_text(images_dir / name, f"IMAGES[{json.dumps(key)}] = {json.dumps(img)};\n")
            scripts += f'<script src="{IMAGES_DIR}/{name}"></script>\n'
        payload = "{}"
    data = json.dumps({"frames": sorted(frames.values(), key=lambda f: (f["sequence"] or "", f["frame"] or 0, f["file"])),
                       "temporal": temporal, "config": {k: report["config"].get(k) for k in ("data_dir", "runs", "device")}})
    html = _PAGE.replace("/*DATA*/", data).replace("/*IMAGES*/", payload).replace("<!--SCRIPTS-->", scripts)
    path = out_dir / "viewer.html"
    write_text(path, html)
    return path


_PAGE = r"""<!doctype html>
<html><head><meta charset="utf-8"><title>jaxdenoise bench viewer</title>
<style>
body{font:13px sans-serif;margin:0;background:#1e1e1e;color:#ddd}
header{padding:6px 10px;background:#2a2a2a;display:flex;gap:14px;align-items:center;flex-wrap:wrap}
select,input,button{font:inherit}
#grid{display:flex;flex-wrap:wrap;gap:8px;padding:8px}
.panel{background:#111;border:2px solid #333;width:300px}
.panel.active{border-color:#e8b100}
.view{width:300px;height:300px;overflow:hidden;position:relative;cursor:grab;background:#000}
.view canvas{position:absolute;left:0;top:0;transform-origin:0 0;image-rendering:pixelated}
.cap{padding:3px 5px;white-space:nowrap;overflow:hidden;text-overflow:ellipsis}
.failed{color:#f77;padding:8px;white-space:normal}
.note{color:#e8b100;padding:0 5px 3px;white-space:normal}
#legend{display:flex;align-items:center;gap:4px}
#legend canvas{width:160px;height:12px}
#legend[hidden]{display:none}
</style></head><body>
<header>
<b>jaxdenoise viewer</b>
<label>frame <select id="frame"></select></label>
<label>exposure <input id="ev" type="range" min="-8" max="8" step="0.25" value="0"> <span id="evv">0 EV</span></label>
<label><input id="err" type="checkbox"> error maps (e)</label>
<span id="legend" hidden>1e-4 <canvas id="legbar" width="160" height="1"></canvas> 10 (relative squared error)</span>
<button id="play" hidden>play (space)</button>
<span id="info"></span>
<span>keys: left/right method, up/down frame, e error, wheel zoom, drag pan</span>
</header>
<div id="grid"></div>
<pre id="selftest" hidden></pre>
<script>
var ERRORS = [];
window.onerror = function(m, s, l){ ERRORS.push(m + " (line " + l + ")"); };
var _ce = console.error; console.error = function(){ ERRORS.push(Array.from(arguments).join(" ")); _ce.apply(console, arguments); };
var DATA = /*DATA*/;
var IMAGES = /*IMAGES*/;
</script>
<!--SCRIPTS-->
<script>
var decoded = {};
function half(h){ var s=(h&0x8000)?-1:1, e=(h>>10)&31, f=h&1023;
  if(e===0) return s*Math.pow(2,-14)*(f/1024); if(e===31) return f?NaN:s*Infinity; return s*Math.pow(2,e-15)*(1+f/1024); }
var HALF = new Float32Array(65536); for (var i=0;i<65536;i++) HALF[i]=half(i);
function decode(id){ if(decoded[id]) return decoded[id]; var im=IMAGES[id]; if(!im) return null;
  var bin=atob(im.data), u=new Uint16Array(bin.length/2);
  for(var i=0;i<u.length;i++) u[i]=bin.charCodeAt(2*i)|(bin.charCodeAt(2*i+1)<<8);
  var f=new Float32Array(u.length); for(var j=0;j<u.length;j++) f[j]=HALF[u[j]];
  return decoded[id]={w:im.w,h:im.h,px:f}; }
function ramp(t){ // false colour, dark blue -> yellow
  var c=[[13,8,135],[126,3,168],[204,71,120],[248,149,64],[240,249,33]]; t=Math.max(0,Math.min(1,t))*(c.length-1);
  var i=Math.min(c.length-2,Math.floor(t)), u=t-i; return [0,1,2].map(function(k){return c[i][k]*(1-u)+c[i+1][k]*u;}); }
var state={frame:0, active:0, scale:1, ox:0, oy:0, err:false, ev:0, playing:null};
function draw(canvas, img, ref){
  canvas.width=img.w; canvas.height=img.h; var ctx=canvas.getContext("2d"), out=ctx.createImageData(img.w,img.h);
  var k=Math.pow(2,state.ev), n=img.w*img.h;
  for(var p=0;p<n;p++){ var o=4*p;
    if(state.err && ref){ var e=0; for(var c=0;c<3;c++){ var x=img.px[3*p+c], r=ref.px[3*p+c]; e+=(x-r)*(x-r)/(r*r+0.01);} e/=3;
      var col=ramp((Math.log10(Math.max(e,1e-4))+4)/5); out.data[o]=col[0]; out.data[o+1]=col[1]; out.data[o+2]=col[2]; }
    else { for(var c2=0;c2<3;c2++){ var v=Math.max(0,Math.min(1,img.px[3*p+c2]*k)); out.data[o+c2]=Math.round(255*Math.pow(v,1/2.2)); } }
    out.data[o+3]=255; }
  ctx.putImageData(out,0,0); }
function fmt(v,d){ return (v===null||v===undefined)?"-":Number(v).toPrecision(d); }
function panels(){
  var f=DATA.frames[state.frame], ref=f.reference?decode(f.reference):null, list=[{method:"reference", image:f.reference}].concat(f.methods);
  var grid=document.getElementById("grid"); grid.innerHTML="";
  list.forEach(function(m,i){
    var d=document.createElement("div"); d.className="panel"+(i===state.active?" active":""); d.dataset.method=m.method;
    var cap=document.createElement("div"); cap.className="cap";
    var t=f.sequence?DATA.temporal[f.sequence+"|"+f.file.split("/").pop()+"|"+m.method]:undefined;
    cap.textContent=m.method+(m.relmse!==undefined?"  RelMSE "+fmt(m.relmse,4)+"  SSIM "+fmt(m.ssim,4)+"  "+
      (m.seconds===null||m.seconds===undefined?"- ms":(1e3*m.seconds).toFixed(1)+" ms"):"")+(t!==undefined&&t!==null?"  temporal "+fmt(t,3):"");
    cap.dataset.relmse=m.relmse===undefined?"":m.relmse; d.appendChild(cap);
    if(m.notes&&m.notes.length){ var nt=document.createElement("div"); nt.className="note"; nt.textContent="note: "+m.notes.join("; "); d.appendChild(nt); }
    if(m.failed){ var fl=document.createElement("div"); fl.className="failed"; fl.textContent="failed: "+m.failed; d.appendChild(fl); }
    else { var v=document.createElement("div"); v.className="view"; var c=document.createElement("canvas"); v.appendChild(c); d.appendChild(v);
      var img=decode(m.image); if(img){ draw(c,img,m.method==="reference"?null:ref); } }
    d.onclick=function(){ state.active=i; panels(); };
    grid.appendChild(d); });
  transform(); document.getElementById("info").textContent=f.file+"  spp "+f.spp; }
function transform(){ document.querySelectorAll(".view canvas").forEach(function(c){
  c.style.transform="translate("+state.ox+"px,"+state.oy+"px) scale("+state.scale*300/Math.max(c.width,c.height)+")"; }); }
var drag=null;
document.addEventListener("wheel",function(e){ if(!e.target.closest(".view")) return; e.preventDefault();
  var z=e.deltaY<0?1.25:0.8, r=e.target.closest(".view").getBoundingClientRect(), mx=e.clientX-r.left, my=e.clientY-r.top;
  state.ox=mx-(mx-state.ox)*z; state.oy=my-(my-state.oy)*z; state.scale*=z; transform(); },{passive:false});
document.addEventListener("mousedown",function(e){ if(e.target.closest(".view")) drag={x:e.clientX-state.ox,y:e.clientY-state.oy}; });
document.addEventListener("mousemove",function(e){ if(drag){ state.ox=e.clientX-drag.x; state.oy=e.clientY-drag.y; transform(); } });
document.addEventListener("mouseup",function(){ drag=null; });
function setFrame(i){ state.frame=(i+DATA.frames.length)%DATA.frames.length; document.getElementById("frame").value=state.frame; panels(); }
document.addEventListener("keydown",function(e){ var n=DATA.frames[state.frame].methods.length+1;
  if(e.key==="ArrowRight"){ state.active=(state.active+1)%n; panels(); } else if(e.key==="ArrowLeft"){ state.active=(state.active+n-1)%n; panels(); }
  else if(e.key==="ArrowDown"){ setFrame(state.frame+1); } else if(e.key==="ArrowUp"){ setFrame(state.frame-1); }
  else if(e.key==="e"){ var b=document.getElementById("err"); b.checked=!b.checked; b.onchange(); }
  else if(e.key===" "){ e.preventDefault(); document.getElementById("play").onclick(); } });
var sel=document.getElementById("frame");
DATA.frames.forEach(function(f,i){ var o=document.createElement("option"); o.value=i; o.textContent=(f.sequence?f.sequence+" #"+f.frame+" ":"")+f.file; sel.appendChild(o); });
sel.onchange=function(){ setFrame(+sel.value); };
document.getElementById("ev").oninput=function(){ state.ev=+this.value; document.getElementById("evv").textContent=this.value+" EV"; panels(); };
document.getElementById("err").onchange=function(){ state.err=this.checked; document.getElementById("legend").hidden=!this.checked; panels(); };
(function(){ var c=document.getElementById("legbar"), x=c.getContext("2d"); for(var i=0;i<160;i++){ var col=ramp(i/159); x.fillStyle="rgb("+col.map(Math.round)+")"; x.fillRect(i,0,1,1);} })();
if(DATA.frames.some(function(f){return f.sequence;})){ var pb=document.getElementById("play"); pb.hidden=false;
  pb.onclick=function(){ if(state.playing){ clearInterval(state.playing); state.playing=null; return; }
    var seq=DATA.frames[state.frame].sequence; state.playing=setInterval(function(){ var j=state.frame+1;
      if(j>=DATA.frames.length||DATA.frames[j].sequence!==seq){ j=DATA.frames.findIndex(function(f){return f.sequence===seq;}); } setFrame(j); },250); }; }
if(DATA.frames.length) setFrame(0);
if(location.hash==="#selftest"){
  var res={frames:DATA.frames.length, images:0, undecoded:[], switch_changes:null, numbers_ok:true, errors:null};
  Object.keys(IMAGES).forEach(function(k){ var d=decode(k); if(d&&d.w>0&&d.h>0&&d.px.length===3*d.w*d.h) res.images++; else res.undecoded.push(k); });
  var caps=document.querySelectorAll(".cap"); var f=DATA.frames[0];
  f.methods.forEach(function(m,i){ var shown=caps[i+1].dataset.relmse; if(m.relmse!==undefined && Number(shown)!==m.relmse) res.numbers_ok=false; });
  var cs=document.querySelectorAll(".view canvas"), i0=cs.length>=3?1:0;
  if(cs.length>=2){ var a=cs[i0].getContext("2d").getImageData(0,0,cs[i0].width,cs[i0].height).data, b=cs[i0+1].getContext("2d").getImageData(0,0,cs[i0+1].width,cs[i0+1].height).data;
    var diff=0; for(var q=0;q<Math.min(a.length,b.length);q++) diff+=Math.abs(a[q]-b[q]); res.switch_changes=diff>0; }
  res.errors=ERRORS; var pre=document.getElementById("selftest"); pre.textContent=JSON.stringify(res); pre.hidden=false; }
</script></body></html>
"""
