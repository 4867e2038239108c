import torch, kornia
exec(open(__file__.rsplit('/', 1)[0] + '/chroma.py').read().split('tot={}')[0])
def cfl(net, low, num, den):
    L=lin(kornia.filters.gaussian_blur2d(low.permute(2,0,1)[None],(9,9),(3,3)).clamp(0,1))
    c=(L+num)/(L.mean(1,keepdim=True)+den)
    E=lin(net.permute(2,0,1)[None].clamp(0,1)); Y=E.mean(1,keepdim=True)
    return srgb((Y*c).clamp(0,1))[0].permute(1,2,0)
for s in ["sofa","chair"]:
    d=torch.load(f"/tmp/exp/{s}.pt"); te=[v for v in d.values() if v["split"]=="test"]
    for num,den in [(0,1e-4),(1e-4,1e-4),(1e-5,1e-5),(0,1e-5)]:
        ims=[cfl(v["net"].float(),v["low"].float(),num,den) for v in te]
        print(s,num,den,"%.2f"%(sum(psnr(i,v["truth"].float()) for i,v in zip(ims,te))/len(te)))
