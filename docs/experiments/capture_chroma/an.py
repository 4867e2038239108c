import torch, kornia
from naka_gs_plugin.enhance.exposure import lift_gamma, apply_gamma, scene_mean
def psnr(a,b): return float(-10*torch.log10(((a-b)**2).mean()))
def ssim(a,b): return float(kornia.metrics.ssim(a.permute(2,0,1)[None],b.permute(2,0,1)[None],11).mean())
def sat(x):
    mx=x.max(-1).values; mn=x.min(-1).values
    return float(((mx-mn)/(mx+1e-3)).mean())
tot={}
for s in ["bike","chair","shrub","sofa"]:
    d=torch.load(f"/tmp/exp/{s}.pt")
    tr=[v for v in d.values() if v["split"]=="train"]; te=[v for v in d.values() if v["split"]=="test"]
    f=lambda vs,k:[v[k].float() for v in vs]
    m={k:scene_mean(f(tr,k)) for k in ["low","naka","net","truth"]}
    st={k:sat(torch.cat([x.reshape(-1,3) for x in f(tr,k)])) for k in ["naka","net","truth"]}
    g_mg=lift_gamma(f(tr,"net"))
    g_nk=lift_gamma(f(tr,"net"), target=m["naka"]) if m["naka"]>m["net"] else 1.0
    g_or=lift_gamma(f(tr,"net"), target=m["truth"])
    print(s, {k:round(v,3) for k,v in m.items()}, "sat", {k:round(v,3) for k,v in st.items()}, "g_mg %.3f g_naka %.3f g_oracle %.3f"%(g_mg,g_nk,g_or))
    variants={"naka":lambda v:v["naka"].float(),"net":lambda v:v["net"].float(),
      "net+mg":lambda v:apply_gamma([v["net"].float()],g_mg)[0],
      "net+nakamean":lambda v:apply_gamma([v["net"].float()],g_nk)[0],
      "net+oracle":lambda v:apply_gamma([v["net"].float()],g_or)[0]}
    for k,fn in variants.items():
        p=[psnr(fn(v),v["truth"].float()) for v in te]; q=[ssim(fn(v),v["truth"].float()) for v in te]
        P=sum(p)/len(p); Q=sum(q)/len(q); tot.setdefault(k,[]).append((P,Q))
        print("   %-14s %.2f %.3f"%(k,P,Q))
for k,v in tot.items(): print("MEAN %-14s %.2f %.3f"%(k,sum(a for a,_ in v)/4,sum(b for _,b in v)/4))
